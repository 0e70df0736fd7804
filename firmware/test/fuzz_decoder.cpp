// libFuzzer target for the firmware's frame reader and the controller behind it. Checks, on any input:
// no crash or out-of-bounds access (ASan, UBSan); every accepted frame has a correct CRC by an independent
// bitwise CRC and the exact payload length of its id; and the controller's safety invariants hold, the steppers'
// too (released and still while a fault is latched, within their speed limit, every step inside its window).
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "core/controller.h"
#include "core/frame.h"

// Bitwise CRC-16/MCRF4XX, written from the definition (reflected poly 0x8408, init 0xFFFF, no final xor).
static uint16_t reference_crc(const uint8_t* data, size_t len) {
    uint16_t crc = 0xFFFF;
    for (size_t i = 0; i < len; ++i) {
        crc ^= data[i];
        for (int bit = 0; bit < 8; ++bit) crc = (crc & 1) ? (uint16_t)((crc >> 1) ^ 0x8408) : (uint16_t)(crc >> 1);
    }
    return crc;
}

// Plain COBS decoding from the definition; returns the body length or -1.
static int reference_cobs(const uint8_t* in, size_t len, uint8_t* out) {
    size_t i = 0, n = 0;
    while (i < len) {
        size_t code = in[i];
        if (code == 0 || i + code > len) return -1;
        for (size_t k = 1; k < code; ++k) out[n++] = in[i + k];
        i += code;
        if (code != 0xFF && i < len) out[n++] = 0;
    }
    return (int)n;
}

static void require(bool condition) {
    if (!condition) abort();
}

static void fuzz_reader(const uint8_t* data, size_t size) {
    core::FrameReader reader(true);
    size_t frame_start = 0;
    for (size_t i = 0; i < size; ++i) {
        bool accepted = reader.feed(data[i]);
        if (accepted) {
            uint8_t body[512];
            int len = reference_cobs(data + frame_start, i - frame_start, body);
            require(len >= 4 && len <= proto::MAX_BODY_BYTES);
            require(reference_crc(body, (size_t)len - 2) == (uint16_t)(body[len - 2] | body[len - 1] << 8));
            require(body[0] == reader.msg_id() && body[1] == reader.seq());
            require(proto::payload_size(reader.msg_id()) == reader.payload_len());
            require(memcmp(body + 2, reader.payload(), reader.payload_len()) == 0);
        }
        if (data[i] == 0) frame_start = i + 1;
    }
}

static bool sink(const uint8_t*, uint8_t len, void*) { return len <= core::MAX_FRAME_BYTES; }

static void check_invariants(const core::Controller& c) {
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        require(c.max_pressure_pa(i) > 0 && c.max_pressure_pa(i) <= core::PRESSURE_CEILING_PA);
        require(c.setpoint_pa(i) >= 0 && c.setpoint_pa(i) <= c.max_pressure_pa(i));
        if (c.fault_flags() || c.setpoint_pa(i) == 0) require(c.drive(i) == 0);
        require(c.drive(i) <= c.pid(i).gains().max_drive);
    }
    if (c.fault_flags()) require(c.motion_enabled_mask() == 0);
    for (uint8_t n = 0; n < core::AXES; ++n) {
        const core::Axis& axis = c.motion().axis(n);
        require(axis.velocity_q24() <= axis.max_velocity_q24());
        if (!axis.configured()) require(axis.state() == proto::MOTION_STATE_ABSENT && !axis.enabled());
    }
}

// The next window's steps: none while a fault is latched, one axis at most, at most MAX_STEPS_PER_WINDOW, inside
// the window.
static void check_plan(const core::Controller& c) {
    const core::StepPlan& plan = c.step_plan();
    require(!(plan.axis[0].count && plan.axis[1].count));
    for (uint8_t n = 0; n < core::AXES; ++n) {
        const core::AxisSteps& steps = plan.axis[n];
        if (c.fault_flags()) require(steps.count == 0);
        require(steps.count <= core::MAX_STEPS_PER_WINDOW);
        if (steps.count) require(steps.first_q6 >= 64 && steps.first_q6 < core::WINDOW_Q6);
        if (steps.count > 1) require((uint32_t)steps.first_q6 + (steps.count - 1UL) * steps.interval_q6 < core::WINDOW_Q6 * 1.01);
    }
}

// The first bytes choose the ADC readings; the rest is the received stream, with a tick after every 8 bytes.
static void fuzz_controller(const uint8_t* data, size_t size) {
    static core::Controller controller;
    controller = core::Controller();
    // Odd-length inputs also offer their tail as a stored settings block (decoded, mostly refused as corrupt).
    const uint8_t* stored = size % 2 && size >= core::SETTINGS_BYTES ? data + size - core::SETTINGS_BYTES : 0;
    controller.init(proto::BOARD_NATIVE, proto::RESET_CAUSE_POWER_ON, sink, 0, stored);
    proto::Hello hello = {proto::PROTOCOL_VERSION, proto::SPEC_HASH};
    uint8_t payload[proto::Hello::PAYLOAD_SIZE];
    proto::encode(hello, payload);
    uint8_t frame[core::MAX_FRAME_BYTES];
    uint8_t len = core::frame_encode(proto::MSG_HELLO, 0, payload, sizeof payload, frame);
    for (uint8_t i = 0; i < len; ++i) controller.receive(frame[i]);
    require(controller.session_open());

    core::AdcTick adc;
    for (uint8_t i = 0; i < core::CHAMBERS; ++i) {
        adc.sum[i] = (uint16_t)(4 * (size > i ? data[i] * 4 : 512));
        adc.count[i] = 4;
    }
    adc.bandgap_counts = 225;  // 5.0 V
    for (size_t i = core::CHAMBERS; i < size; ++i) {
        controller.receive(data[i]);
        check_invariants(controller);
        if (i % 8 == 0) {
            core::MotionSample sample = {(uint8_t)(data[i] >> 6), data[i] % 5 == 0, {0, 0}};
            controller.tick(adc, data[i] % 3, sample);
            check_invariants(controller);
            check_plan(controller);
        }
    }
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    fuzz_reader(data, size);
    fuzz_controller(data, size);
    return 0;
}
