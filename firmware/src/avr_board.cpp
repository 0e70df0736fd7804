#include "avr_board.h"

#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <util/atomic.h>

#include "board_pins.h"

// MCUSR as found at reset, and the watchdog interrupt's mark; in .noinit because .init3 runs before .bss is
// cleared, and so that the mark survives the watchdog reset that follows it.
static uint8_t reset_flags __attribute__((section(".noinit")));
static uint32_t watchdog_mark __attribute__((section(".noinit")));
static const uint32_t WATCHDOG_MARK = 0x57444F47UL;  // "WDOG"

// Runs in .init3, before the C runtime and the Arduino core: keep the reset flags and the mark, clear both,
// and stop a watchdog left running by a watchdog reset (it would otherwise reset again during start-up).
// (Optiboot 4.4 leaves nothing meaningful in r2, so r2 is not read.)
extern "C" void capture_reset_flags() __attribute__((naked, used, section(".init3")));
extern "C" void capture_reset_flags() {
    reset_flags = MCUSR;
    MCUSR = 0;
    wdt_disable();
}

// Map the reset flags to the protocol's reset cause; power-on wins because it sets the others' meaning aside.
// With MCUSR cleared by a bootloader, only the watchdog's mark can tell anything.
uint8_t avr_reset_cause() {
    static int8_t cause = -1;
    if (cause >= 0) return (uint8_t)cause;
    bool watchdog_marked = watchdog_mark == WATCHDOG_MARK;
    watchdog_mark = 0;
    if (reset_flags & _BV(PORF)) cause = proto::RESET_CAUSE_POWER_ON;
    else if (reset_flags & _BV(WDRF)) cause = proto::RESET_CAUSE_WATCHDOG;
    else if (reset_flags & _BV(BORF)) cause = proto::RESET_CAUSE_BROWN_OUT;
    else if (reset_flags & _BV(EXTRF)) cause = proto::RESET_CAUSE_EXTERNAL;
    else if (watchdog_marked) cause = proto::RESET_CAUSE_WATCHDOG;
    else cause = proto::RESET_CAUSE_UNKNOWN;
    return (uint8_t)cause;
}

// Conversions per chamber per tick, then two of the 1.1 V reference (the first after switching the
// multiplexer to it is not settled): 14 conversions of 104 us each fit inside the 2 ms tick.
static const uint8_t SAMPLES_PER_TICK = 4;
static const uint8_t SENSOR_CONVERSIONS = SAMPLES_PER_TICK * core::CHAMBERS;
static const uint8_t CHAIN_CONVERSIONS = SENSOR_CONVERSIONS + 2;
#if defined(__AVR_ATmega2560__)
static const uint8_t BANDGAP_MUX = 0x1E;  // MUX5 (in ADCSRB) stays 0
#else
static const uint8_t BANDGAP_MUX = 0x0E;
#endif
// The ADC chain's state, touched only by the two interrupt handlers (which never nest), so not volatile.
static uint16_t adc_sum[core::CHAMBERS];
static uint8_t adc_count[core::CHAMBERS];
static uint16_t adc_bandgap;
static uint8_t adc_channel;
static uint8_t adc_done;
// The sums latched at the latest tick, read by the main loop with interrupts off (cli/sei are memory
// barriers), and how many ticks are waiting for it.
static core::AdcTick latched;
static volatile uint16_t ticks_pending;

// Start a chain of conversions that visits the chambers in turn, SAMPLES_PER_TICK times each.
static void start_adc_chain() {
    adc_channel = 0;
    adc_done = 0;
    ADMUX = _BV(REFS0);
    ADCSRA |= _BV(ADSC);
}

// ADC conversion complete: add the reading, then start the next conversion of the chain.
ISR(ADC_vect) {
    uint16_t value = ADC;
    uint8_t done = ++adc_done;
    if (done <= SENSOR_CONVERSIONS) {
        adc_sum[adc_channel] += value;
        ++adc_count[adc_channel];
        adc_channel = adc_channel + 1 == core::CHAMBERS ? 0 : adc_channel + 1;
    } else if (done == CHAIN_CONVERSIONS) {
        adc_bandgap = value;
        return;
    }
    ADMUX = _BV(REFS0) | (done < SENSOR_CONVERSIONS ? adc_channel : BANDGAP_MUX);
    ADCSRA |= _BV(ADSC);
}

// Timer0 compare match at 500 Hz: a control tick; latch the ADC sums and start the next chain.
ISR(TIMER0_COMPA_vect) {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        latched.sum[i] = adc_sum[i];
        latched.count[i] = adc_count[i];
        adc_sum[i] = 0;
        adc_count[i] = 0;
    }
    latched.bandgap_counts = adc_bandgap;
    adc_bandgap = 0;
    start_adc_chain();
    ++ticks_pending;
}

// Watchdog interrupt (interrupt-and-reset mode): the main loop has not kicked for 120 ms. Stop the blowers and
// leave the mark the next start reads (a bootloader clears MCUSR); the hardware resets 120 ms later.
ISR(WDT_vect) {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) avr_set_drive(i, 0);
    watchdog_mark = WATCHDOG_MARK;
}

// Pins, timers and ADC. The blower pins were inputs from reset until here: the pull-downs of
// docs/hardware.md hold the drivers off meanwhile (through a bootloader's wait too).
void avr_hardware_init() {
    BLOWER0_PORT &= ~_BV(BLOWER0_BIT);
    BLOWER1_PORT &= ~_BV(BLOWER1_BIT);
    BLOWER2_PORT &= ~_BV(BLOWER2_BIT);
    BLOWER0_DDR |= _BV(BLOWER0_BIT);
    BLOWER1_DDR |= _BV(BLOWER1_BIT);
    BLOWER2_DDR |= _BV(BLOWER2_BIT);
    LED_PORT &= ~_BV(LED_BIT);
    LED_DDR |= _BV(LED_BIT);
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        // Timer1: fast PWM mode 14 (TOP = ICR1), clk/1, outputs disconnected until a drive level is set.
        // Stopped while TOP is written and started last, so that no period ever runs with a stale TOP.
        TCCR1B = 0;
        TIMSK1 = 0;
        ICR1 = PWM_TOP;
        OCR1A = 0;
        OCR1B = 0;
        TCNT1 = 0;
        TCCR1A = _BV(WGM11);
        TCCR1B = _BV(WGM13) | _BV(WGM12) | _BV(CS10);
        // Timer2: fast PWM mode 3 (TOP = 0xFF), clk/1, output disconnected: the same 62.5 kHz and 256 steps.
        TCCR2B = 0;
        OCR2B = 0;
        TCNT2 = 0;
        TIMSK2 = 0;
        TCCR2A = _BV(WGM21) | _BV(WGM20);
        TCCR2B = _BV(CS20);
        // Timer0: CTC (TOP = OCR0A), clk/256, the compare interrupt is the tick; the core's overflow is off.
        TCCR0B = 0;
        TIMSK0 = 0;
        TCCR0A = _BV(WGM01);
        OCR0A = TICK_TIMER0_TOP;
        TCNT0 = 0;
        TIFR0 = _BV(OCF0A) | _BV(TOV0);
        TIMSK0 = _BV(OCIE0A);
        TCCR0B = _BV(CS02);
        // ADC: AVcc reference, clk/128 (125 kHz), single conversions chained by the ADC interrupt.
        ADCSRB = 0;
        ADCSRA = _BV(ADEN) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0);
        start_adc_chain();
    }
}

// Whether the tick interrupt has latched a tick the loop has not taken yet.
bool avr_tick_pending() { return ticks_pending != 0; }

// Watchdog in interrupt-and-system-reset mode, 120 ms to the interrupt and 120 ms more to the reset: about the
// 250 ms to a reset of a plain watchdog, with the blowers off after half of it.
void avr_watchdog_start() {
    wdt_enable(WDTO_120MS);
    WDTCSR |= _BV(WDIE);
}

// Restart the watchdog's count, and re-arm its interrupt (the hardware clears WDIE when it fires).
void avr_watchdog_kick() {
    wdt_reset();
    WDTCSR |= _BV(WDIE);
}

// Copy the latched tick out with interrupts off so the sums and counts belong to the same tick.
bool avr_take_tick(core::AdcTick& adc, uint16_t& missed_ticks) {
    bool pending = false;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        if (ticks_pending) {
            pending = true;
            missed_ticks = ticks_pending - 1;
            ticks_pending = 0;
            adc = latched;
        }
    }
    return pending;
}

// Compare value for a drive level, drive * PWM_TOP / 65535 to within one step, without a division.
static uint8_t compare_value(uint16_t drive) {
    return (uint8_t)(((uint32_t)drive * PWM_TOP + 32768u) >> 16);
}

// Connect the pin with the compare value, or disconnect it (pin low) when the value is 0.
void avr_set_drive(uint8_t chamber, uint16_t drive) {
    uint8_t value = compare_value(drive);
    if (chamber == 0) {
        OCR1A = value;
        if (value) TCCR1A |= _BV(COM1A1);
        else TCCR1A &= ~_BV(COM1A1);
    } else if (chamber == 1) {
        OCR1B = value;
        if (value) TCCR1A |= _BV(COM1B1);
        else TCCR1A &= ~_BV(COM1B1);
    } else {
        OCR2B = value;
        if (value) TCCR2A |= _BV(COM2B1);
        else TCCR2A &= ~_BV(COM2B1);
    }
}

#ifdef PHANTOM_PROBE
void avr_led(bool) {}
void avr_probe(bool high) {
#else
void avr_probe(bool) {}
void avr_led(bool high) {
#endif
    if (high) LED_PORT |= _BV(LED_BIT);
    else LED_PORT &= ~_BV(LED_BIT);
}

// The block lives at the start of the EEPROM.
static uint8_t* const SETTINGS_ADDRESS = (uint8_t*)0;
static uint8_t settings_pending[core::SETTINGS_BYTES];
static uint8_t settings_next = core::SETTINGS_BYTES;  // the next byte to program; SETTINGS_BYTES = none

void avr_settings_read(uint8_t block[core::SETTINGS_BYTES]) {
    eeprom_read_block(block, SETTINGS_ADDRESS, core::SETTINGS_BYTES);
}

void avr_settings_write(const uint8_t block[core::SETTINGS_BYTES]) {
    for (uint8_t i = 0; i < core::SETTINGS_BYTES; ++i) settings_pending[i] = block[i];
    settings_next = 0;
}

// One byte when the EEPROM is idle; unchanged bytes are skipped (eeprom_update_byte), which spares the cells.
void avr_settings_service() {
    while (settings_next < core::SETTINGS_BYTES && eeprom_is_ready()) {
        uint8_t i = settings_next++;
        if (eeprom_read_byte(SETTINGS_ADDRESS + i) == settings_pending[i]) continue;
        eeprom_write_byte(SETTINGS_ADDRESS + i, settings_pending[i]);
        return;
    }
}

// All three blower pins disconnected and low, then a spin the watchdog ends (its interrupt first).
void avr_hang() {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) avr_set_drive(i, 0);
    for (;;) {
    }
}
