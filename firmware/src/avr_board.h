// The thin AVR layer: registers for the PWM timers, the interrupt-driven ADC, the control tick, the stepper
// outputs, the watchdog, the reset cause, EEPROM and the status LED. Everything else lives in core/.
#pragma once
#include <stdint.h>

#include "core/controller.h"

// All three blower channels alike: 8-bit fast PWM at 16 MHz / 256 = 62.5 kHz (Timer1 in mode 14 with
// TOP = ICR1 = 255, Timer2 in mode 3), far above the RC filter that turns it into the blower driver's amplitude
// input (docs/hardware.md). Compare value = drive * PWM_TOP / 65535.
const uint8_t PWM_TOP = 0xFF;
// The control tick: Timer0 in CTC mode, 16 MHz / 256 / (124 + 1) = 500 Hz (Timer0 is taken from the Arduino
// core, whose millis() the firmware does not use).
const uint8_t TICK_TIMER0_TOP = 124;

// The reset cause: MCUSR as found before the C runtime started. A stock bootloader (Optiboot 4.4, the Mega's
// stk500v2) clears MCUSR before the application runs: then it is UNKNOWN, unless the watchdog's interrupt left
// its mark in RAM just before the watchdog reset the board (WATCHDOG).
uint8_t avr_reset_cause();

// Blower pins low and disconnected, stepper drivers released, PWM timers, the tick interrupt and the
// free-running ADC chain.
void avr_hardware_init();

// Arm the watchdog: after 120 ms without a kick its interrupt stops the blowers and marks RAM, and 120 ms
// later it resets the board.
void avr_watchdog_start();

// Kick the watchdog.
void avr_watchdog_kick();

// Whether a control tick is waiting (call with interrupts off to decide whether to sleep).
bool avr_tick_pending();

// Take the ADC sums and the motion inputs of the latest tick if one is pending; missed_ticks counts ticks nobody
// took.
bool avr_take_tick(core::AdcTick& adc, uint16_t& missed_ticks, core::MotionSample& motion);

// Hand over the steps of the next window (the plan must stay intact until that window has ended): Timer0's
// compare B interrupt puts each on its STEP pin in its slot (16 us), after the tick interrupt that starts the
// window has set the DIR pins. Call after the control tick that started a window (MotionSample.window_start).
void avr_motion_load(const core::StepPlan& plan);

// Enable the stepper drivers of the axes in the mask (EN low) and release the others (EN high); a released
// axis gets no further STEP pulse.
void avr_motion_enable(uint8_t axes_mask);

// Set a chamber's drive level (0..65535 = 0..1); 0 disconnects the pin so the output is exactly off.
void avr_set_drive(uint8_t chamber, uint16_t drive);

// The status LED on D13 (or, in a PHANTOM_PROBE build, the tick probe: high while the control step runs).
void avr_led(bool on);
void avr_probe(bool high);

// The settings block in EEPROM: read it at start; write a new one a byte at a time, never waiting for the
// EEPROM (a byte takes 3.4 ms to program), from the main loop.
void avr_settings_read(uint8_t block[core::SETTINGS_BYTES]);
void avr_settings_write(const uint8_t block[core::SETTINGS_BYTES]);
void avr_settings_service();

// The serial link: USART0 at 115200 8N1 (as the Arduino core's Serial sets it: U2X, UBRR 16), received and sent
// bytes each in a 128-byte ring served by its interrupt. avr_serial_send queues a whole frame or nothing (false:
// no room now); avr_serial_flush waits until every queued byte has left the transmitter.
void avr_serial_begin();
uint8_t avr_serial_available();
uint8_t avr_serial_read();
bool avr_serial_send(const uint8_t* bytes, uint8_t len);
void avr_serial_flush();

// Blowers off, stepper drivers released, and spin without kicking the watchdog (interrupts on, as in a stuck
// main loop): TEST_HANG's end.
void avr_hang() __attribute__((noreturn));
