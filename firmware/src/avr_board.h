// The thin AVR layer: registers for the PWM timers, the interrupt-driven ADC, the control tick, the
// watchdog and the reset cause. Everything else lives in core/.
#pragma once
#include <stdint.h>

#include "core/controller.h"

// Timer1 (mode 14, TOP = ICR1) and Timer2 (8-bit fast PWM) compare values for drive level 1.
const uint16_t TIMER1_TOP = 1999;  // 16 MHz / 8 / 2000 = 1 kHz PWM; every second overflow is a tick
const uint8_t TIMER2_TOP = 0xFF;   // 16 MHz / 32 / 256 = 1.95 kHz PWM

// The reset cause read from MCUSR (or from Optiboot's copy in r2) before the C runtime started.
uint8_t avr_reset_cause();

// Blower pins low and disconnected, PWM timers, the tick interrupt and the free-running ADC chain.
void avr_hardware_init();

// Arm the watchdog (system reset after 250 ms without a kick).
void avr_watchdog_start();

// Kick the watchdog.
void avr_watchdog_kick();

// Whether a control tick is waiting (call with interrupts off to decide whether to sleep).
bool avr_tick_pending();

// Take the ADC sums of the latest tick if one is pending; missed_ticks counts ticks nobody took.
bool avr_take_tick(core::AdcTick& adc, uint16_t& missed_ticks);

// Set a chamber's drive level (0..65535 = 0..1); 0 disconnects the pin so the output is exactly off.
void avr_set_drive(uint8_t chamber, uint16_t drive);

// Drive the tick probe pin (high while the control step runs, for cycle counting on a bench).
void avr_probe(bool high);

// Blowers off, interrupts off, and spin without kicking the watchdog: TEST_HANG's end.
void avr_hang() __attribute__((noreturn));
