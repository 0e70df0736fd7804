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
static core::MotionSample latched_motion;
// The steppers at the latest tick, for the steps not made yet: the stepping axis's steps left, whether the plan
// handed over was still waiting (avr_take_tick counts them into the sample it gives the loop).
static uint8_t latched_steps_left, latched_stepping_axis;
static bool latched_plan_waiting;
static volatile uint16_t ticks_pending;

// The stepper outputs. The main loop hands over a plan once per window (next_plan, while plan_ready); at the
// window's start the tick interrupt takes the steps of its moving axis (one at most: core/motion.h), counted
// down in steps_left with the time of the next in whole slots from the window's start (next_step_slot) and 64ths
// of a slot (next_step_frac), and the compare B interrupt makes them. Only these two interrupts touch that
// state, and they never nest.
static const core::StepPlan* volatile next_plan;
static volatile bool plan_ready;
static uint8_t window_tick = core::WINDOW_TICKS - 1;  // so that the first tick starts a window
static uint16_t window_base_slot;                      // the running tick's first slot within its window
static uint8_t stepping_axis;
static uint8_t stepping_bit;  // its STEP bit
static uint8_t steps_left;
static uint16_t next_step_slot;
static uint8_t next_step_frac;
static uint16_t interval_slots;
static uint8_t interval_frac;
static volatile uint8_t enabled_step_bits;  // a released axis is never pulsed
static const uint8_t STEP_BITS[4] = {0, _BV(STEP0_BIT), _BV(STEP1_BIT), _BV(STEP0_BIT) | _BV(STEP1_BIT)};
static const uint8_t DIR_BITS[4] = {0, _BV(DIR0_BIT), _BV(DIR1_BIT), _BV(DIR0_BIT) | _BV(DIR1_BIT)};
// A STEP pulse is high for at least 2 us (32 cycles), and low at least as long between two pulses made back to
// back (a late or flushed step): above the A4988's 1 us and the DRV8825's 1.9 us (the TMC2209 needs 100 ns). The
// compare B interrupt's bookkeeping between the rising and the falling edge takes 36 cycles (the harness measures
// every pulse: tests/test_motion_sim.py).
static const uint8_t STEP_LOW_CYCLES = 32;

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

// The window's steps not made when it ends (an interrupt ran late, or a time rounded past its end): made now.
static void flush_steps() {
    for (; steps_left; --steps_left) {
        uint8_t bit = stepping_bit & enabled_step_bits;
        STEP_PORT |= bit;
        __builtin_avr_delay_cycles(STEP_LOW_CYCLES);
        STEP_PORT &= (uint8_t)~bit;
        __builtin_avr_delay_cycles(STEP_LOW_CYCLES);
    }
}

// The slot within the running tick of the next step (at least 1: a late one is due at once), or 0 when there is
// none in this tick.
static inline uint8_t pending_step_slot() __attribute__((always_inline));
static inline uint8_t pending_step_slot() {
    if (!steps_left) return 0;
    uint16_t base = window_base_slot;
    if (next_step_slot <= base) return 1;
    uint16_t offset = next_step_slot - base;
    return offset < core::SLOTS_PER_TICK ? (uint8_t)offset : 0;
}

// Compare B at the running tick's next step, or off.
static void arm_steps() {
    uint8_t slot = pending_step_slot();
    if (!slot) {
        TIMSK0 &= (uint8_t)~_BV(OCIE0B);
        return;
    }
    OCR0B = slot;
    TIFR0 = _BV(OCF0B);
    TIMSK0 |= _BV(OCIE0B);
}

// Every tick: a new window takes the plan handed over (its DIR levels first: the first step comes a slot later
// at the earliest, tens of us of set-up time where the drivers need under 1 us); then the home inputs and the
// steps not made yet are sampled for the main loop, and compare B is armed for this tick.
static void run_steppers_tick() {
    if (++window_tick == core::WINDOW_TICKS) {
        window_tick = 0;
        window_base_slot = 0;
        flush_steps();
        latched_motion.window_start = true;
        if (plan_ready) {
            const core::StepPlan* plan = next_plan;
            plan_ready = false;
            DIR_PORT = (uint8_t)((DIR_PORT & ~DIR_BITS[3]) | DIR_BITS[plan->dir_high & 3]);
            stepping_axis = plan->axis[0].count ? 0 : 1;
            stepping_bit = STEP_BITS[1 + stepping_axis];
            const core::AxisSteps& steps = plan->axis[stepping_axis];
            steps_left = steps.count;
            next_step_slot = steps.first_q6 >> 6;
            next_step_frac = steps.first_q6 & 63;
            interval_slots = steps.interval_q6 >> 6;
            interval_frac = steps.interval_q6 & 63;
        }
    } else {
        window_base_slot += core::SLOTS_PER_TICK;
    }
    uint8_t home = HOME_PIN;
    latched_motion.home_inputs = (uint8_t)(((home >> HOME0_BIT) & 1) | (((home >> HOME1_BIT) & 1) << 1));
    latched_steps_left = steps_left;
    latched_stepping_axis = stepping_axis;
    latched_plan_waiting = plan_ready;
    arm_steps();
}

// Timer0 compare match B: the stepping axis's next step. The pin goes high, the next step's slot is found
// meanwhile, and it goes low 2 us later. A step whose slot has passed by then (a late interrupt) is made at once.
ISR(TIMER0_COMPB_vect) {
    for (;;) {
        uint8_t bit = stepping_bit & enabled_step_bits;
        STEP_PORT |= bit;
        --steps_left;
        uint8_t frac = (uint8_t)(next_step_frac + interval_frac);
        uint16_t next = next_step_slot + interval_slots;
        if (frac & 64) {
            ++next;
            frac &= 63;
        }
        next_step_frac = frac;
        next_step_slot = next;
        uint8_t slot = pending_step_slot();
        if (slot) OCR0B = slot;
        STEP_PORT &= (uint8_t)~bit;
        if (!slot) {
            TIMSK0 &= (uint8_t)~_BV(OCIE0B);
            return;
        }
        if (slot > TCNT0) return;  // its match is still to come
        TIFR0 = _BV(OCF0B);        // due already: made now, its match (if it fired) forgotten
        __builtin_avr_delay_cycles(STEP_LOW_CYCLES);
    }
}

// Timer0 compare match at 500 Hz: a control tick; latch the ADC sums and start the next chain, and the next
// steps.
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
    run_steppers_tick();
    ++ticks_pending;
}

// ---- serial ------------------------------------------------------------------------------------------------
// The Arduino core's Serial took about 110 cycles a byte to queue a frame through its virtual write() and 120 a
// byte in its interrupt: 7 % of the CPU at 50 Hz telemetry. Here a frame is copied into the ring at once.
#if defined(__AVR_ATmega2560__)
#define SERIAL_RX_VECT USART0_RX_vect
#define SERIAL_UDRE_VECT USART0_UDRE_vect
#else
#define SERIAL_RX_VECT USART_RX_vect
#define SERIAL_UDRE_VECT USART_UDRE_vect
#endif
static const uint8_t SERIAL_RING_BYTES = 128;  // a power of two: indices wrap with a mask
static const uint8_t SERIAL_RING_MASK = SERIAL_RING_BYTES - 1;
static uint8_t rx_ring[SERIAL_RING_BYTES];
static uint8_t tx_ring[SERIAL_RING_BYTES];
static volatile uint8_t rx_head, rx_tail, tx_head, tx_tail;  // head: where the next byte goes

// A received byte into the ring; dropped when the ring is full (the frame it belongs to fails its CRC).
ISR(SERIAL_RX_VECT) {
    uint8_t byte = UDR0;
    uint8_t head = rx_head;
    uint8_t next = (uint8_t)((head + 1) & SERIAL_RING_MASK);
    if (next == rx_tail) return;
    rx_ring[head] = byte;
    rx_head = next;
}

// The transmitter's data register is free: the next queued byte, or no more interrupts when none is left.
ISR(SERIAL_UDRE_VECT) {
    uint8_t tail = tx_tail;
    if (tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_ring[tail];
    tx_tail = (uint8_t)((tail + 1) & SERIAL_RING_MASK);
}

void avr_serial_begin() {
    UCSR0A = _BV(U2X0);
    UBRR0 = (F_CPU / 4 / 115200 - 1) / 2;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

uint8_t avr_serial_available() { return (uint8_t)((rx_head - rx_tail) & SERIAL_RING_MASK); }

uint8_t avr_serial_read() {
    uint8_t tail = rx_tail;
    uint8_t byte = rx_ring[tail];
    rx_tail = (uint8_t)((tail + 1) & SERIAL_RING_MASK);
    return byte;
}

bool avr_serial_send(const uint8_t* bytes, uint8_t len) {
    uint8_t head = tx_head;
    uint8_t room = (uint8_t)((tx_tail - head - 1) & SERIAL_RING_MASK);
    if (room < len) return false;
    for (uint8_t i = 0; i < len; ++i) {
        tx_ring[head] = bytes[i];
        head = (uint8_t)((head + 1) & SERIAL_RING_MASK);
    }
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        tx_head = head;
        UCSR0A = (uint8_t)((UCSR0A & _BV(U2X0)) | _BV(TXC0));  // cleared: set again once all has gone out
        UCSR0B |= _BV(UDRIE0);
    }
    return true;
}

void avr_serial_flush() {
    while ((UCSR0B & _BV(UDRIE0)) || !(UCSR0A & _BV(TXC0))) {
    }
}

// Every driver released (EN high) and no further step: the watchdog's interrupt, a hang, a fault.
static void release_steppers() {
    enabled_step_bits = 0;
    TIMSK0 &= (uint8_t)~_BV(OCIE0B);
    EN0_PORT |= _BV(EN0_BIT);
    EN1_PORT |= _BV(EN1_BIT);
}

// Watchdog interrupt (interrupt-and-reset mode): the main loop has not kicked for 120 ms. Stop the blowers and
// leave the mark the next start reads (a bootloader clears MCUSR); the hardware resets 120 ms later.
ISR(WDT_vect) {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) avr_set_drive(i, 0);
    release_steppers();
    watchdog_mark = WATCHDOG_MARK;
}

// Pins, timers and ADC. The blower pins were inputs from reset until here: the pull-downs of
// docs/hardware.md hold the drivers off meanwhile (through a bootloader's wait too), as the EN pull-ups of
// docs/hardware.md hold the stepper drivers released.
void avr_hardware_init() {
    BLOWER0_PORT &= ~_BV(BLOWER0_BIT);
    BLOWER1_PORT &= ~_BV(BLOWER1_BIT);
    BLOWER2_PORT &= ~_BV(BLOWER2_BIT);
    BLOWER0_DDR |= _BV(BLOWER0_BIT);
    BLOWER1_DDR |= _BV(BLOWER1_BIT);
    BLOWER2_DDR |= _BV(BLOWER2_BIT);
    LED_PORT &= ~_BV(LED_BIT);
    LED_DDR |= _BV(LED_BIT);
    EN0_PORT |= _BV(EN0_BIT);
    EN1_PORT |= _BV(EN1_BIT);
    EN0_DDR |= _BV(EN0_BIT);
    EN1_DDR |= _BV(EN1_BIT);
    STEP_PORT &= (uint8_t)~STEP_BITS[3];
    STEP_DDR |= STEP_BITS[3];
    DIR_PORT &= (uint8_t)~DIR_BITS[3];
    DIR_DDR |= DIR_BITS[3];
    HOME_DDR &= (uint8_t)~(_BV(HOME0_BIT) | _BV(HOME1_BIT));
    HOME_PORT |= _BV(HOME0_BIT) | _BV(HOME1_BIT);  // pull-ups: a normally closed switch to ground opens high
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
        // Timer0: CTC (TOP = OCR0A), clk/256, the compare A interrupt is the tick, compare B the steps (armed
        // per tick); the core's overflow is off.
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
bool avr_take_tick(core::AdcTick& adc, uint16_t& missed_ticks, core::MotionSample& motion) {
    bool pending = false;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        if (ticks_pending) {
            pending = true;
            missed_ticks = ticks_pending - 1;
            ticks_pending = 0;
            adc = latched;
            motion = latched_motion;
            latched_motion.window_start = false;
            for (uint8_t n = 0; n < core::AXES; ++n)
                motion.unmade_steps[n] = (uint8_t)((n == latched_stepping_axis ? latched_steps_left : 0) +
                                                   (latched_plan_waiting ? next_plan->axis[n].count : 0));
        }
    }
    return pending;
}

// The tick interrupt took the last plan at this window's start: the loop hands over one plan per window.
void avr_motion_load(const core::StepPlan& plan) {
    next_plan = &plan;
    plan_ready = true;
}

void avr_motion_enable(uint8_t axes_mask) {
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        enabled_step_bits = STEP_BITS[axes_mask & 3];
        if (axes_mask & 1) EN0_PORT &= (uint8_t)~_BV(EN0_BIT);
        else EN0_PORT |= _BV(EN0_BIT);
        if (axes_mask & 2) EN1_PORT &= (uint8_t)~_BV(EN1_BIT);
        else EN1_PORT |= _BV(EN1_BIT);
    }
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

// All three blower pins disconnected and low, the steppers released, then a spin the watchdog ends (its
// interrupt first).
void avr_hang() {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) avr_set_drive(i, 0);
    release_steppers();
    for (;;) {
    }
}
