#include "avr_board.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <util/atomic.h>

#include "board_pins.h"

// MCUSR as found at reset; in .noinit because .init3 runs before .bss is cleared.
static uint8_t reset_flags __attribute__((section(".noinit")));

// Runs in .init3, before the C runtime and the Arduino core: keep the reset flags, clear them, and stop a
// watchdog left running by a watchdog reset (it would otherwise reset again during start-up).
extern "C" void capture_reset_flags() __attribute__((naked, used, section(".init3")));
extern "C" void capture_reset_flags() {
    uint8_t flags = MCUSR;
    if (flags == 0) __asm__ __volatile__("mov %0, r2" : "=r"(flags));  // Optiboot passes MCUSR in r2
    reset_flags = flags;
    MCUSR = 0;
    wdt_disable();
}

// Map MCUSR bits to the protocol's reset cause; power-on wins because it sets every flag's meaning aside.
uint8_t avr_reset_cause() {
    if (reset_flags & _BV(PORF)) return proto::RESET_CAUSE_POWER_ON;
    if (reset_flags & _BV(WDRF)) return proto::RESET_CAUSE_WATCHDOG;
    if (reset_flags & _BV(BORF)) return proto::RESET_CAUSE_BROWN_OUT;
    if (reset_flags & _BV(EXTRF)) return proto::RESET_CAUSE_EXTERNAL;
    return proto::RESET_CAUSE_UNKNOWN;
}

// Conversions per chamber per tick: 12 conversions of 104 us each fit well inside the 2 ms tick.
static const uint8_t SAMPLES_PER_TICK = 4;
// The ADC chain's state, touched only by the two interrupt handlers (which never nest), so not volatile.
static uint16_t adc_sum[core::CHAMBERS];
static uint8_t adc_count[core::CHAMBERS];
static uint8_t adc_channel;
static uint8_t adc_conversions_left;
// The sums latched at the latest tick, read by the main loop with interrupts off (cli/sei are memory
// barriers), and how many ticks are waiting for it.
static core::AdcTick latched;
static volatile uint16_t ticks_pending;
static uint8_t overflow_phase;

// Start a chain of conversions that visits the chambers in turn, SAMPLES_PER_TICK times each.
static void start_adc_chain() {
    adc_channel = 0;
    adc_conversions_left = SAMPLES_PER_TICK * core::CHAMBERS;
    ADMUX = _BV(REFS0);
    ADCSRA |= _BV(ADSC);
}

// ADC conversion complete: add the reading, then start the next conversion of the chain on the next channel.
ISR(ADC_vect) {
    uint8_t channel = adc_channel;
    adc_sum[channel] += ADC;
    ++adc_count[channel];
    if (--adc_conversions_left == 0) return;
    channel = channel + 1 == core::CHAMBERS ? 0 : channel + 1;
    adc_channel = channel;
    ADMUX = _BV(REFS0) | channel;
    ADCSRA |= _BV(ADSC);
}

// Timer1 overflow at 1 kHz: every second one is a control tick; latch the ADC sums and start the next chain.
ISR(TIMER1_OVF_vect) {
    overflow_phase ^= 1;
    if (overflow_phase) return;
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        latched.sum[i] = adc_sum[i];
        latched.count[i] = adc_count[i];
        adc_sum[i] = 0;
        adc_count[i] = 0;
    }
    start_adc_chain();
    ++ticks_pending;
}

// Pins, timers and ADC as the Board contract in common.md says.
void avr_hardware_init() {
    BLOWER0_PORT &= ~_BV(BLOWER0_BIT);
    BLOWER1_PORT &= ~_BV(BLOWER1_BIT);
    BLOWER2_PORT &= ~_BV(BLOWER2_BIT);
    BLOWER0_DDR |= _BV(BLOWER0_BIT);
    BLOWER1_DDR |= _BV(BLOWER1_BIT);
    BLOWER2_DDR |= _BV(BLOWER2_BIT);
    PROBE_PORT &= ~_BV(PROBE_BIT);
    PROBE_DDR |= _BV(PROBE_BIT);
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        // Timer1: fast PWM mode 14 (TOP = ICR1), clk/8, outputs disconnected until a drive level is set.
        // Stopped while TOP is written and started last, so that no period ever runs with a stale TOP.
        TCCR1B = 0;
        ICR1 = TIMER1_TOP;
        OCR1A = 0;
        OCR1B = 0;
        TCNT1 = 0;
        TCCR1A = _BV(WGM11);
        TIMSK1 = _BV(TOIE1);
        TCCR1B = _BV(WGM13) | _BV(WGM12) | _BV(CS11);
        // Timer2: fast PWM mode 3 (TOP = 0xFF), clk/32, output disconnected.
        TCCR2B = 0;
        OCR2B = 0;
        TCNT2 = 0;
        TIMSK2 = 0;
        TCCR2A = _BV(WGM21) | _BV(WGM20);
        TCCR2B = _BV(CS21) | _BV(CS20);
        // ADC: AVcc reference, clk/128 (125 kHz), single conversions chained by the ADC interrupt.
        ADCSRB = 0;
        ADCSRA = _BV(ADEN) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0);
        start_adc_chain();
    }
}

// Whether the tick interrupt has latched a tick the loop has not taken yet.
bool avr_tick_pending() { return ticks_pending != 0; }

// Watchdog in system-reset mode, 250 ms.
void avr_watchdog_start() { wdt_enable(WDTO_250MS); }

// Restart the watchdog's count.
void avr_watchdog_kick() { wdt_reset(); }

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

// Compare value for a drive level, drive * top / 65535 to within one step, without a division.
static uint16_t compare_value(uint16_t drive, uint16_t top) {
    return (uint16_t)(((uint32_t)drive * top + 32768u) >> 16);
}

// Connect the pin with the compare value, or disconnect it (pin low) when the value is 0.
void avr_set_drive(uint8_t chamber, uint16_t drive) {
    if (chamber == 0) {
        uint16_t value = compare_value(drive, TIMER1_TOP);
        OCR1A = value;
        if (value) TCCR1A |= _BV(COM1A1);
        else TCCR1A &= ~_BV(COM1A1);
    } else if (chamber == 1) {
        uint16_t value = compare_value(drive, TIMER1_TOP);
        OCR1B = value;
        if (value) TCCR1A |= _BV(COM1B1);
        else TCCR1A &= ~_BV(COM1B1);
    } else {
        uint8_t value = (uint8_t)compare_value(drive, TIMER2_TOP);
        OCR2B = value;
        if (value) TCCR2A |= _BV(COM2B1);
        else TCCR2A &= ~_BV(COM2B1);
    }
}

// The probe pin follows the control step, for cycle counting from outside.
void avr_probe(bool high) {
    if (high) PROBE_PORT |= _BV(PROBE_BIT);
    else PROBE_PORT &= ~_BV(PROBE_BIT);
}

// All three blower pins disconnected and low, then a spin the watchdog ends.
void avr_hang() {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) avr_set_drive(i, 0);
    cli();
    for (;;) {
    }
}
