// Pin map of each supported board: the three blower PWM outputs (OC1A, OC1B, OC2B) and the status LED (D13;
// the tick probe instead in a PHANTOM_PROBE build).
// Sensors are on ADC channels 0, 1, 2 (A0, A1, A2) on both boards.
#pragma once
#include <avr/io.h>

#include "core/protocol_generated.h"

#if defined(__AVR_ATmega328P__)
// Uno: OC1A = D9 = PB1, OC1B = D10 = PB2, OC2B = D3 = PD3; LED D13 = PB5.
#define PHANTOM_BOARD proto::BOARD_UNO
#define BLOWER0_DDR DDRB
#define BLOWER0_PORT PORTB
#define BLOWER0_BIT PB1
#define BLOWER1_DDR DDRB
#define BLOWER1_PORT PORTB
#define BLOWER1_BIT PB2
#define BLOWER2_DDR DDRD
#define BLOWER2_PORT PORTD
#define BLOWER2_BIT PD3
#define LED_DDR DDRB
#define LED_PORT PORTB
#define LED_BIT PB5
#elif defined(__AVR_ATmega2560__)
// Mega 2560: OC1A = D11 = PB5, OC1B = D12 = PB6, OC2B = D9 = PH6; LED D13 = PB7.
#define PHANTOM_BOARD proto::BOARD_MEGA2560
#define BLOWER0_DDR DDRB
#define BLOWER0_PORT PORTB
#define BLOWER0_BIT PB5
#define BLOWER1_DDR DDRB
#define BLOWER1_PORT PORTB
#define BLOWER1_BIT PB6
#define BLOWER2_DDR DDRH
#define BLOWER2_PORT PORTH
#define BLOWER2_BIT PH6
#define LED_DDR DDRB
#define LED_PORT PORTB
#define LED_BIT PB7
#else
#error "unsupported board: build for the ATmega328P (Uno) or the ATmega2560 (Mega)"
#endif
