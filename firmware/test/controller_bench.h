// The native tests' controller bench: a Controller wired to a captured transport, fed real frames, with the
// ADC readings and the motion inputs each tick chosen by the test; the frames the board sends are decoded.
#pragma once
#include <vector>

#include "core/controller.h"
#include "core/frame.h"
#include "plant.h"

using namespace core;
using namespace proto;

// One whole wire frame.
inline std::vector<uint8_t> frame_of(uint8_t id, uint8_t seq, const uint8_t* payload, uint8_t len) {
    uint8_t out[MAX_FRAME_BYTES];
    uint8_t n = frame_encode(id, seq, payload, len, out);
    return std::vector<uint8_t>(out, out + n);
}

// The AVR layer's stepper outputs (firmware/src/avr_board.cpp) for the native tests: windows of WINDOW_TICKS
// ticks; at a window's start the rest of the running plan is made and the plan handed over takes its place; the
// running plan's steps are made when their time comes. Steps are counted as the drivers see them (+1 with DIR
// high, only while the axis's driver is enabled), each with its time; a home switch can be wired to each axis's
// made position.
struct StepperModel {
    struct Switch {
        bool wired;
        int32_t edge;       // active at and beyond this made position ...
        bool active_below;  // ... below it (true) or above it
    };
    uint8_t window_tick = WINDOW_TICKS - 1;
    long ticks = 0;
    bool plan_ready = false;
    StepPlan next = {0, {{0, 0, 0}, {0, 0, 0}}};
    StepPlan running = {0, {{0, 0, 0}, {0, 0, 0}}};
    long running_start_tick = 0;
    uint8_t made[AXES] = {0, 0};
    int32_t pulses[AXES] = {0, 0};
    int32_t ignored_pulses[AXES] = {0, 0};
    std::vector<double> pulse_times_s[AXES];
    Switch switches[AXES] = {{false, 0, true}, {false, 0, true}};

    // Make the running plan's steps due before `until_q6` (Q6 slots from its window's start).
    void make_due(uint16_t until_q6, uint8_t enabled) {
        for (uint8_t n = 0; n < AXES; ++n) {
            const AxisSteps& steps = running.axis[n];
            while (made[n] < steps.count) {
                uint32_t at_q6 = steps.first_q6 + (uint32_t)made[n] * steps.interval_q6;
                if (at_q6 >= until_q6 && until_q6 < WINDOW_Q6) break;
                ++made[n];
                if (!(enabled >> n & 1)) {
                    ++ignored_pulses[n];
                    continue;
                }
                pulses[n] += running.dir_high >> n & 1 ? 1 : -1;
                pulse_times_s[n].push_back(running_start_tick * 1.0 / TICK_HZ + at_q6 / 64.0 * 16e-6);
            }
        }
    }
    uint8_t home_inputs() const {
        uint8_t levels = 0;
        for (uint8_t n = 0; n < AXES; ++n) {
            const Switch& s = switches[n];
            bool active = s.wired && (s.active_below ? pulses[n] <= s.edge : pulses[n] >= s.edge);
            if (active) levels |= (uint8_t)(1u << n);
        }
        return levels;
    }
    // The tick interrupt: the sample the loop gets for this tick.
    MotionSample tick(uint8_t enabled) {
        MotionSample sample;
        if (++window_tick == WINDOW_TICKS) {
            window_tick = 0;
            make_due(WINDOW_Q6, enabled);
            running = plan_ready ? next : StepPlan{running.dir_high, {{0, 0, 0}, {0, 0, 0}}};
            plan_ready = false;
            running_start_tick = ticks;
            made[0] = made[1] = 0;
        } else {
            make_due((uint16_t)(window_tick * SLOTS_PER_TICK * 64), enabled);
        }
        ++ticks;
        sample.window_start = window_tick == 0;
        sample.home_inputs = home_inputs();
        for (uint8_t n = 0; n < AXES; ++n)
            sample.unmade_steps[n] = (uint8_t)(running.axis[n].count - made[n] + (plan_ready ? next.axis[n].count : 0));
        return sample;
    }
    void hand_over(const StepPlan& plan) {
        next = plan;
        plan_ready = true;
    }
};

// A controller wired to a captured transport and a sensor model; frames the board sends are decoded.
struct Bench {
    struct Sent {
        uint8_t id, seq;
        std::vector<uint8_t> payload;
    };
    Controller controller;
    FrameReader board_frames{true};
    std::vector<Sent> sent;
    uint16_t counts[CHAMBERS] = {512, 512, 512};
    uint8_t conversions[CHAMBERS] = {4, 4, 4};  // 0: a stalled ADC
    uint16_t bandgap_counts = 225;              // 1.1 V against a 5.0 V supply
    StepperModel steppers;
    uint8_t host_seq = 0;
    bool transport_full = false;

    static bool capture(const uint8_t* frame, uint8_t len, void* context) {
        Bench* bench = static_cast<Bench*>(context);
        if (bench->transport_full) return false;
        for (uint8_t i = 0; i < len; ++i) {
            if (bench->board_frames.feed(frame[i])) {
                const FrameReader& r = bench->board_frames;
                bench->sent.push_back(Sent{r.msg_id(), r.seq(), std::vector<uint8_t>(r.payload(), r.payload() + r.payload_len())});
            }
        }
        return true;
    }

    explicit Bench(uint8_t reset_cause = RESET_CAUSE_POWER_ON, const uint8_t* stored = 0) {
        controller.init(BOARD_NATIVE, reset_cause, capture, this, stored);
    }

    void feed(const std::vector<uint8_t>& bytes) {
        for (uint8_t b : bytes) controller.receive(b);
    }
    uint8_t command(uint8_t id, const uint8_t* payload, uint8_t len) {
        uint8_t seq = host_seq++;
        feed(frame_of(id, seq, payload, len));
        return seq;
    }
    void hello(uint32_t hash = SPEC_HASH) {
        uint8_t p[Hello::PAYLOAD_SIZE];
        Hello h = {PROTOCOL_VERSION, hash};
        encode(h, p);
        command(MSG_HELLO, p, sizeof p);
    }
    uint8_t setpoints(int16_t a, int16_t b, int16_t c) {
        SetSetpoints m = {{a, b, c}};
        uint8_t p[SetSetpoints::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_SET_SETPOINTS, p, sizeof p);
    }
    uint8_t simple(uint8_t id) { return command(id, 0, 0); }
    uint8_t config(uint16_t period_ms, uint16_t deadline_ms) {
        SetConfig m = {period_ms, deadline_ms};
        uint8_t p[SetConfig::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_SET_CONFIG, p, sizeof p);
    }
    uint8_t set_pid(uint8_t chamber, float kp, float ki, float kd, int16_t max_pa, uint16_t max_drive) {
        SetPid m = {chamber, kp, ki, kd, max_pa, max_drive};
        uint8_t p[SetPid::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_SET_PID, p, sizeof p);
    }
    void set_pressure(uint8_t chamber, double pressure_pa) { counts[chamber] = plant::adc_counts(pressure_pa); }
    // Run until the start-up zero is measured (the readings are still from the start).
    void boot() { ticks(ZERO_SETTLE_TICKS + ZERO_TICKS + 1); }
    void ticks(int n) {
        for (int i = 0; i < n; ++i) {
            AdcTick adc;
            for (uint8_t c = 0; c < CHAMBERS; ++c) {
                adc.sum[c] = (uint16_t)(conversions[c] * counts[c]);
                adc.count[c] = conversions[c];
            }
            adc.bandgap_counts = bandgap_counts;
            MotionSample sample = steppers.tick(controller.motion_enabled_mask());
            controller.tick(adc, 0, sample);
            if (sample.window_start) steppers.hand_over(controller.step_plan());
        }
    }
    // The status of the last ACK/NACK for a command seq (-1 if none); is_ack tells which kind.
    int reply_status(uint8_t seq, bool* is_ack = 0) const {
        for (size_t i = sent.size(); i-- > 0;) {
            const Sent& s = sent[i];
            if ((s.id == MSG_ACK || s.id == MSG_NACK) && s.payload[1] == seq) {
                if (is_ack) *is_ack = s.id == MSG_ACK;
                return s.payload[2];
            }
        }
        return -1;
    }
    int count(uint8_t id) const {
        int n = 0;
        for (const Sent& s : sent) n += s.id == id;
        return n;
    }
    const Sent* last(uint8_t id) const {
        for (size_t i = sent.size(); i-- > 0;)
            if (sent[i].id == id) return &sent[i];
        return 0;
    }
};
