// The phantom controller's sketch: the Arduino entry points that join the AVR layer to the core.
#include <Arduino.h>
#include <avr/sleep.h>

#include "avr_board.h"
#include "board_pins.h"
#include "core/controller.h"

static core::Controller controller;
static uint16_t applied_drive[core::CHAMBERS];
static uint16_t saved_generation;

// The core's transport: Serial's TX buffer, never blocking (a frame that does not fit is dropped).
static bool send_frame(const uint8_t* frame, uint8_t len, void*) {
    if (Serial.availableForWrite() < len) return false;
    Serial.write(frame, len);
    return true;
}

// Write a chamber's drive level to its timer only when it changed.
static void apply_drives() {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        uint16_t drive = controller.drive(i);
        if (drive == applied_drive[i]) continue;
        avr_set_drive(i, drive);
        applied_drive[i] = drive;
    }
}

// Sleep (idle mode: timers, ADC and UART keep running) until a tick or a received byte is waiting; other
// interrupts (ADC, UART transmit, millis) wake the CPU only for this short check.
static void idle() {
    set_sleep_mode(SLEEP_MODE_IDLE);
    for (;;) {
        cli();
        if (avr_tick_pending() || Serial.available()) break;
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
    Serial.begin(115200);
    uint8_t block[core::SETTINGS_BYTES];
    avr_settings_read(block);
    controller.init(PHANTOM_BOARD, avr_reset_cause(), send_frame, 0, block);
    saved_generation = controller.settings_generation();
    avr_watchdog_start();
}

// Received bytes first (bounded by the RX buffer), then at most one control tick, then sleep; the watchdog is
// kicked only after a tick, so a stalled timer or a stuck loop both end in a reset.
void loop() {
    for (uint8_t n = 0; n < SERIAL_RX_BUFFER_SIZE && Serial.available(); ++n) controller.receive((uint8_t)Serial.read());
    core::AdcTick adc;
    uint16_t missed_ticks;
    if (avr_take_tick(adc, missed_ticks)) {
        avr_probe(true);
        controller.tick(adc, missed_ticks);
        avr_probe(false);
        avr_watchdog_kick();
        avr_led(controller.status_led_on());
        save_settings();
    }
    apply_drives();
    avr_settings_service();
    if (controller.hang_requested()) {
        Serial.flush();
        avr_hang();
    }
    idle();
}
