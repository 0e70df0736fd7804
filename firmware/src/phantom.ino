// The phantom controller's sketch: the Arduino entry points that join the AVR layer to the core.
#include <Arduino.h>
#include <avr/sleep.h>

#include "avr_board.h"
#include "board_pins.h"
#include "core/controller.h"

static core::Controller controller;
static uint16_t applied_drive[core::CHAMBERS];
static uint8_t applied_motion_enable;
static uint16_t saved_generation;

// The core's transport: the serial transmit ring, never blocking (a frame that does not fit is dropped).
static bool send_frame(const uint8_t* frame, uint8_t len, void*) { return avr_serial_send(frame, len); }

// Write a chamber's drive level to its timer only when it changed.
static void apply_drives() {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        uint16_t drive = controller.drive(i);
        if (drive == applied_drive[i]) continue;
        avr_set_drive(i, drive);
        applied_drive[i] = drive;
    }
}

// Enable or release the stepper drivers when the controller changes them (at once after a fault or a refused
// HELLO, not only at a tick).
static void apply_motion_enable() {
    uint8_t mask = controller.motion_enabled_mask();
    if (mask == applied_motion_enable) return;
    avr_motion_enable(mask);
    applied_motion_enable = mask;
}

// Sleep (idle mode: timers, ADC and UART keep running) until a tick or a received byte is waiting; other
// interrupts (ADC, UART transmit, steps) wake the CPU only for this short check.
static void idle() {
    set_sleep_mode(SLEEP_MODE_IDLE);
    for (;;) {
        cli();
        if (avr_tick_pending() || avr_serial_available()) break;
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
}

// Hand a changed settings block to the EEPROM writer.
static void save_settings() {
    if (controller.settings_generation() == saved_generation) return;
    saved_generation = controller.settings_generation();
    uint8_t block[core::SETTINGS_BYTES];
    controller.settings(block);
    avr_settings_write(block);
}

// Hardware up with blowers off, then the core with the stored settings, then the watchdog.
void setup() {
    avr_hardware_init();
    avr_serial_begin();
    uint8_t block[core::SETTINGS_BYTES];
    avr_settings_read(block);
    controller.init(PHANTOM_BOARD, avr_reset_cause(), send_frame, 0, block);
    saved_generation = controller.settings_generation();
    avr_watchdog_start();
}

// Received bytes first (bounded by the RX buffer), then at most one control tick (and the steppers' next
// window when one starts),
// then sleep; the watchdog is kicked only after a tick, so a stalled timer or a stuck loop both end in a reset.
// The drivers' enable follows the controller before the tick (a command may have changed it) and after it.
void loop() {
    for (uint8_t n = avr_serial_available(); n; --n) controller.receive(avr_serial_read());
    apply_motion_enable();
    core::AdcTick adc;
    uint16_t missed_ticks;
    core::MotionSample motion;
    if (avr_take_tick(adc, missed_ticks, motion)) {
        avr_probe(true);
        controller.tick(adc, missed_ticks, motion);
        apply_motion_enable();
        if (motion.window_start) avr_motion_load(controller.step_plan());
        avr_probe(false);
        avr_watchdog_kick();
        avr_led(controller.status_led_on());
        save_settings();
    }
    apply_drives();
    avr_settings_service();
    if (controller.hang_requested()) {
        avr_serial_flush();
        avr_hang();
    }
    idle();
}
