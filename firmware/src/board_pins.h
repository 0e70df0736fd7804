// Pin map of each supported board: the three blower PWM outputs (OC1A, OC1B, OC2B), the status LED (D13; the
// tick probe instead in a PHANTOM_PROBE build), and the scanner's two stepper drivers (STEP, DIR, EN each, both
// STEP pins on one port so that one write pulses both) with their home switch inputs.
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
// Steppers: STEP D2 (PD2) and D4 (PD4), DIR D5 (PD5) and D6 (PD6), EN D7 (PD7) and D8 (PB0); home switches A3
// (PC3) and A4 (PC4). Axis 0 is the orbit, axis 1 the elevation.
#define STEP_DDR DDRD
#define STEP_PORT PORTD
#define STEP0_BIT PD2
#define STEP1_BIT PD4
#define DIR_DDR DDRD
#define DIR_PORT PORTD
#define DIR0_BIT PD5
#define DIR1_BIT PD6
#define EN0_DDR DDRD
#define EN0_PORT PORTD
#define EN0_BIT PD7
#define EN1_DDR DDRB
#define EN1_PORT PORTB
#define EN1_BIT PB0
#define HOME_DDR DDRC
#define HOME_PORT PORTC
#define HOME_PIN PINC
#define HOME0_BIT PC3
#define HOME1_BIT PC4
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
// Steppers, all on port A: STEP D22 (PA0) and D23 (PA1), DIR D24 (PA2) and D25 (PA3), EN D26 (PA4) and D27
// (PA5); home switches D28 (PA6) and D29 (PA7).
#define STEP_DDR DDRA
#define STEP_PORT PORTA
#define STEP0_BIT PA0
#define STEP1_BIT PA1
#define DIR_DDR DDRA
#define DIR_PORT PORTA
#define DIR0_BIT PA2
#define DIR1_BIT PA3
#define EN0_DDR DDRA
#define EN0_PORT PORTA
#define EN0_BIT PA4
#define EN1_DDR DDRA
#define EN1_PORT PORTA
#define EN1_BIT PA5
#define HOME_DDR DDRA
#define HOME_PORT PORTA
#define HOME_PIN PINA
#define HOME0_BIT PA6
#define HOME1_BIT PA7
#else
#error "unsupported board: build for the ATmega328P (Uno) or the ATmega2560 (Mega)"
#endif
