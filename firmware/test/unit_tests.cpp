// Native unit tests of the firmware core: framing, sensor conversion, the PID against a plant and a float
// reference, and the controller's commands, faults and deadlines through real frames.
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include <vector>

#include "check.h"
#include "controller_bench.h"
#include "core/cobs.h"
#include "core/controller.h"
#include "core/crc16.h"
#include "core/frame.h"
#include "core/sensor.h"
#include "plant.h"

using namespace core;
using namespace proto;

// ---- framing ---------------------------------------------------------------------------------------

TEST(crc_matches_the_catalogue_check_value) {
    const uint8_t text[] = {'1', '2', '3', '4', '5', '6', '7', '8', '9'};
    CHECK_EQ(crc16(text, sizeof text), 0x6F91);
}

TEST(cobs_matches_published_examples) {
    struct Example {
        std::vector<uint8_t> raw, encoded;
    };
    std::vector<uint8_t> long_raw, long_encoded(1, 0xFF);
    for (int i = 1; i < 255; ++i) long_raw.push_back((uint8_t)i);
    long_encoded.insert(long_encoded.end(), long_raw.begin(), long_raw.end());
    long_encoded.push_back(0x01);
    const Example examples[] = {
        {{0x00}, {0x01, 0x01}},
        {{0x00, 0x00}, {0x01, 0x01, 0x01}},
        {{0x00, 0x11, 0x00}, {0x01, 0x02, 0x11, 0x01}},
        {{0x11, 0x22, 0x00, 0x33}, {0x03, 0x11, 0x22, 0x02, 0x33}},
        {{0x11, 0x22, 0x33, 0x44}, {0x05, 0x11, 0x22, 0x33, 0x44}},
        {{0x11, 0x00, 0x00, 0x00}, {0x02, 0x11, 0x01, 0x01, 0x01}},
        {long_raw, long_encoded},
    };
    for (const Example& e : examples) {
        uint8_t out[300];
        uint16_t len = cobs_encode(e.raw.data(), (uint16_t)e.raw.size(), out);
        CHECK(std::vector<uint8_t>(out, out + len) == e.encoded);
        int back = cobs_decode(e.encoded.data(), (uint16_t)e.encoded.size(), out);
        CHECK(back >= 0 && std::vector<uint8_t>(out, out + back) == e.raw);
    }
    const uint8_t past_end[] = {0x05, 0x01, 0x02};
    const uint8_t zero_inside[] = {0x03, 0x00, 0x02};
    uint8_t out[8];
    CHECK_EQ(cobs_decode(past_end, sizeof past_end, out), -1);
    CHECK_EQ(cobs_decode(zero_inside, sizeof zero_inside, out), -1);
}

TEST(reader_takes_frames_split_anywhere_with_garbage_between) {
    uint8_t ping[4] = {1, 2, 3, 4};
    std::vector<uint8_t> good = frame_of(MSG_PING, 9, ping, 4);
    const uint8_t garbage[] = {0x13, 0x37, 0xFF, 0x00, 0x00, 0x05, 0x01, 0x00, 0x42};
    std::vector<uint8_t> stream(garbage, garbage + sizeof garbage);
    stream.push_back(0x00);
    for (int i = 0; i < 3; ++i) {
        stream.insert(stream.end(), good.begin(), good.end());
        stream.insert(stream.end(), garbage, garbage + sizeof garbage);
        stream.push_back(0x00);
    }
    FrameReader reader;
    int frames = 0;
    for (uint8_t byte : stream) {
        if (reader.feed(byte)) {
            ++frames;
            CHECK_EQ(reader.msg_id(), MSG_PING);
            CHECK_EQ(reader.seq(), 9);
            CHECK_EQ(get_u32(reader.payload()), 0x04030201);
        }
    }
    CHECK_EQ(frames, 3);
    CHECK_EQ(reader.frames_ok, 3);
    CHECK(reader.bad_frame + reader.bad_crc >= 4);  // each garbage run ends in at least one bad frame
}

TEST(reader_drops_bad_crc_overflow_board_ids_and_wrong_lengths) {
    uint8_t ping[4] = {0, 0, 0, 0};
    std::vector<uint8_t> frame = frame_of(MSG_PING, 1, ping, 4);
    FrameReader reader;
    std::vector<uint8_t> corrupt = frame;
    corrupt[2] ^= 0x10;
    for (uint8_t b : corrupt) CHECK(!reader.feed(b));
    CHECK_EQ(reader.bad_crc, 1);

    for (int i = 0; i < 100; ++i) CHECK(!reader.feed(0x01));
    CHECK(!reader.feed(0x00));
    CHECK_EQ(reader.overflow, 1);

    std::vector<uint8_t> board_only = frame_of(MSG_TELEMETRY, 1, ping, 4);
    for (uint8_t b : board_only) CHECK(!reader.feed(b));
    std::vector<uint8_t> short_ping = frame_of(MSG_PING, 1, ping, 3);
    for (uint8_t b : short_ping) CHECK(!reader.feed(b));
    CHECK_EQ(reader.bad_frame, 2);

    bool accepted = false;
    for (uint8_t b : frame) accepted = reader.feed(b);
    CHECK(accepted);
    CHECK_EQ(reader.frames_ok, 1);
}

// ---- sensor conversion -----------------------------------------------------------------------------

TEST(sensor_conversion_matches_the_datasheet_across_its_range) {
    // Independent truth: the datasheet's transfer function in double precision, Vout/Vs = 0.018 P + 0.5.
    for (int pressure_pa = -25000; pressure_pa <= 25000; pressure_pa += 250) {
        double counts = 1024.0 * (0.018 * pressure_pa / 1000.0 + 0.5);
        int16_t x16 = (int16_t)lround(counts * 16);
        // Half a sixteenth of a count (1.7 Pa) of rounding in x16, half a Pa of output rounding, and the
        // Q12 constant's 1e-5 relative error (0.25 Pa at 25 kPa).
        CHECK_NEAR(sensor_x16_to_pa(x16, NOMINAL_ZERO_X16), pressure_pa, 2.5);
    }
}

TEST(sensor_round_trips_at_the_range_ends) {
    const int16_t ends_pa[] = {-25000, -24999, -1, 0, 1, 24999, 25000};
    for (int16_t pressure_pa : ends_pa) {
        int16_t x16 = sensor_pa_to_x16(pressure_pa, NOMINAL_ZERO_X16);
        // One sixteenth of a count is 3.39 Pa: the round trip is good to half of that plus half a Pa.
        CHECK_NEAR(sensor_x16_to_pa(x16, NOMINAL_ZERO_X16), pressure_pa, 2.2);
    }
    const int16_t readings_x16[] = {SENSOR_MIN_VALID_X16, NOMINAL_ZERO_X16, SENSOR_MAX_VALID_X16, 0, 1023 * 16};
    for (int16_t x16 : readings_x16) {
        CHECK_EQ(sensor_pa_to_x16(sensor_x16_to_pa(x16, 8000), 8000), x16);
    }
}

TEST(sensor_band_is_0v1_to_4v9) {
    CHECK(!sensor_in_range(sensor_average_x16(20 * 4, 4)));   // 0.098 V
    CHECK(sensor_in_range(sensor_average_x16(21 * 4, 4)));    // 0.103 V
    CHECK(sensor_in_range(sensor_average_x16(1003 * 4, 4)));  // 4.897 V
    CHECK(!sensor_in_range(sensor_average_x16(1004 * 4, 4)));  // 4.902 V
    CHECK_EQ(sensor_average_x16(100 * 3 + 1, 3), 1605);       // 100.33 counts, rounded to sixteenths
    CHECK_EQ(sensor_average_x16(0, 0), 0);
}

// ---- PID -------------------------------------------------------------------------------------------

static const PidGains DEFAULT_GAINS = {DEFAULT_KP_PER_KPA, DEFAULT_KI_PER_KPA_S, DEFAULT_KD_S_PER_KPA, 65535};

struct StepResult {
    double overshoot_fraction;
    double settle_s;  // last time outside +-2 % of the target
    double final_pa;
};

// Closed loop at 500 Hz: the plant integrated at 10 kHz, the sensor read through the ADC model (4 samples).
static StepResult run_step(const PidGains& gains, double target_pa, double seconds) {
    Pid pid;
    pid.init(gains);
    plant::Chamber chamber;
    StepResult result = {0, 0, 0};
    double peak = 0;
    uint16_t drive = 0;
    int ticks = (int)(seconds * TICK_HZ);
    for (int tick = 0; tick < ticks; ++tick) {
        for (int k = 0; k < 20; ++k) chamber.advance(drive / 65535.0, 1.0 / (TICK_HZ * 20));
        int16_t measured = sensor_x16_to_pa(sensor_average_x16(4 * plant::adc_counts(chamber.pressure_pa), 4),
                                            NOMINAL_ZERO_X16 - 8);  // the ADC floors: 0 Pa reads 511.5 on average
        drive = pid.step((int16_t)target_pa, measured);
        if (chamber.pressure_pa > peak) peak = chamber.pressure_pa;
        if (fabs(chamber.pressure_pa - target_pa) > 0.02 * target_pa) result.settle_s = (tick + 1.0) / TICK_HZ;
        CHECK(pid.integral() <= gains.max_drive);
    }
    result.overshoot_fraction = (peak - target_pa) / target_pa;
    result.final_pa = chamber.pressure_pa;
    return result;
}

TEST(pid_step_0_to_2kpa_settles_without_overshoot_on_the_plant) {
    StepResult r = run_step(DEFAULT_GAINS, 2000, 4.0);
    printf("     0 -> 2 kPa: overshoot %.2f %%, settles (2 %%) in %.3f s, final %.1f Pa\n",
           100 * r.overshoot_fraction, r.settle_s, r.final_pa);
    CHECK(r.overshoot_fraction < 0.05);
    CHECK(r.settle_s < 1.0);
    CHECK_NEAR(r.final_pa, 2000, 54.3);  // within one ADC count at steady state
}

TEST(pid_antiwindup_recovers_at_once_after_long_saturation) {
    // max_drive 0.3 cannot hold 3 kPa against the leak: the output saturates for 5 s. Then the target falls to
    // just below the pressure reached. A wound-up integrator (even one clamped to max_drive) would keep the
    // blower running and push the pressure further up; conditional integration leaves nothing to unwind.
    PidGains gains = DEFAULT_GAINS;
    gains.max_drive = (uint16_t)(0.3 * 65535);
    Pid pid;
    pid.init(gains);
    plant::Chamber chamber;
    uint16_t drive = 0;
    for (int tick = 0; tick < 5 * TICK_HZ; ++tick) {
        chamber.advance(drive / 65535.0, 1.0 / TICK_HZ);
        drive = pid.step(3000, (int16_t)chamber.pressure_pa);
        CHECK(drive <= gains.max_drive);
    }
    CHECK_EQ(drive, gains.max_drive);
    CHECK(chamber.pressure_pa < 2500);
    CHECK(pid.integral() < 0.05 * gains.max_drive);
    double switch_pa = chamber.pressure_pa;
    int16_t target = (int16_t)(switch_pa - 100);
    double peak = switch_pa;
    for (int tick = 0; tick < 4 * TICK_HZ; ++tick) {
        chamber.advance(drive / 65535.0, 1.0 / TICK_HZ);
        drive = pid.step(target, (int16_t)chamber.pressure_pa);
        if (tick < 2) CHECK_EQ(drive, 0);
        if (chamber.pressure_pa > peak) peak = chamber.pressure_pa;
    }
    CHECK(peak < switch_pa + 5);  // one tick of the old drive, then nothing more
    CHECK_NEAR(chamber.pressure_pa, target, 20);
}

TEST(pid_output_is_one_sided_and_clamped) {
    Pid pid;
    pid.init(DEFAULT_GAINS);
    CHECK_EQ(pid.step(0, 2000), 0);      // above the setpoint: no negative drive, only off
    CHECK_EQ(pid.step(6000, -6000), 65535);
    PidGains strong = {100, 1000, 1, 40000};
    pid.set_gains(strong);
    for (int i = 0; i < 100; ++i) CHECK(pid.step(32767, -32768) <= 40000);
    for (int i = 0; i < 100; ++i) CHECK_EQ(pid.step(-32768, 32767), 0);
}

// Independent float reference of the same control law, to check the fixed-point arithmetic.
struct FloatPid {
    FloatPid(double kp_, double ki_, double kd_, double max_) : kp(kp_), ki(ki_), kd(kd_), max(max_) {}
    double kp, ki, kd, max, integral = 0, derivative = 0, last_p = 0;
    double step(double sp, double p) {
        double e = sp - p;
        if (kd > 0) derivative += (-kd * (p - last_p) - derivative) / 4;
        last_p = p;
        double prop = kp * e;
        double cand = integral + ki * e;
        double raw = prop + cand + derivative;
        bool winding = (raw > max && e > 0) || (raw < 0 && e < 0);
        if (!winding) integral = cand < 0 ? 0 : (cand > max ? max : cand);
        double u = prop + integral + derivative;
        return u < 0 ? 0 : (u > max ? max : u);
    }
};

TEST(pid_fixed_point_tracks_a_float_reference) {
    srand(7);
    PidGains gains = {1.5f, 4.0f, 0.05f, 60000};
    Pid pid;
    pid.init(gains);
    double dt = 1.0 / TICK_HZ;
    FloatPid ref(1.5e-3, 4.0e-3 * dt, 0.05e-3 / dt, 60000 / 65535.0);
    double worst = 0;
    int16_t p = 0;
    for (int i = 0; i < 20000; ++i) {
        int16_t sp = (int16_t)((i / 2000) * 300);
        p = (int16_t)(p + (rand() % 61) - 30);
        if (p < -500) p = -500;
        if (p > 3500) p = 3500;
        double expected = ref.step(sp, p);
        double got = pid.step(sp, p) / 65535.0;
        worst = fabs(got - expected) > worst ? fabs(got - expected) : worst;
    }
    printf("     fixed point vs float reference: worst difference %.2e of full drive\n", worst);
    CHECK(worst < 2e-4);  // Q28 gains round to 1e-8 relative; the u16 output truncates by < 1.6e-5
}

TEST(pid_gain_change_is_bumpless) {
    const PidGains gentle = {2.0f, 3.0f, 0.0f, 65535};
    Pid pid;
    pid.init(gentle);
    uint16_t before = 0;
    // 200 ticks at a 100 Pa error: P = 0.2, I = 200 * ki e dt = 0.12, well inside the output range.
    for (int i = 0; i < 200; ++i) before = pid.step(2000, 1900);
    CHECK_NEAR(before, 0.32 * 65535, 0.002 * 65535);
    PidGains stronger = gentle;
    stronger.kp_per_kpa = 3.0f;
    pid.set_gains(stronger);
    uint16_t after = pid.step(2000, 1900);
    // Without re-seeding the output would jump by the P change, 0.1; the step itself adds one tick of
    // integral, ki e dt = 6e-4.
    CHECK_NEAR(after, before, 0.001 * 65535);
}

TEST(pid_derivative_acts_on_the_measurement_only) {
    PidGains gains = {1.0f, 0.0f, 0.5f, 65535};
    Pid with_kd, without_kd;
    with_kd.init(gains);
    gains.kd_s_per_kpa = 0;
    without_kd.init(gains);
    with_kd.reset(500);
    without_kd.reset(500);
    for (int i = 0; i < 10; ++i) {
        with_kd.step(1000, 500);
        without_kd.step(1000, 500);
    }
    // A setpoint step at a constant measurement: no derivative kick (P = 0.7, inside the output range).
    CHECK_EQ(with_kd.step(1200, 500), without_kd.step(1200, 500));
    // A rising measurement: the derivative term brakes.
    CHECK(with_kd.step(1200, 510) < without_kd.step(1200, 510) - 0.1 * 65535);
}

TEST(pid_rejects_invalid_gains) {
    PidGains g = DEFAULT_GAINS;
    CHECK(pid_gains_valid(g));
    g.kp_per_kpa = -1;
    CHECK(!pid_gains_valid(g));
    g = DEFAULT_GAINS;
    g.ki_per_kpa_s = NAN;
    CHECK(!pid_gains_valid(g));
    g = DEFAULT_GAINS;
    g.kd_s_per_kpa = INFINITY;
    CHECK(!pid_gains_valid(g));
    g = DEFAULT_GAINS;
    g.kp_per_kpa = MAX_KP_PER_KPA * 1.01f;
    CHECK(!pid_gains_valid(g));
}

// ---- controller ------------------------------------------------------------------------------------

static void check_all_off(const Bench& b) {
    for (uint8_t c = 0; c < CHAMBERS; ++c) {
        CHECK_EQ(b.controller.drive(c), 0);
        CHECK_EQ(b.controller.chamber_state(c), CHAMBER_STATE_FAULT);
        CHECK_EQ(b.controller.setpoint_pa(c), 0);
    }
}

TEST(hello_opens_a_session_and_a_wrong_hash_is_refused) {
    Bench b;
    uint8_t seq = b.setpoints(1000, 0, 0);
    CHECK_EQ(b.reply_status(seq), STATUS_NO_SESSION);
    b.hello(SPEC_HASH ^ 1);
    HelloReply reply;
    decode(reply, b.last(MSG_HELLO_REPLY)->payload.data());
    CHECK_EQ(reply.status, STATUS_SPEC_MISMATCH);
    CHECK_EQ(reply.spec_hash, SPEC_HASH);
    CHECK(!b.controller.session_open());
    b.hello();
    decode(reply, b.last(MSG_HELLO_REPLY)->payload.data());
    CHECK_EQ(reply.status, STATUS_OK);
    CHECK_EQ(reply.reset_cause, RESET_CAUSE_POWER_ON);
    CHECK_EQ(reply.chamber_count, 3);
    CHECK_EQ(reply.fault_flags, 0);
    seq = b.setpoints(1000, 0, 0);
    bool ack = false;
    CHECK_EQ(b.reply_status(seq, &ack), STATUS_OK);
    CHECK(ack);
    b.ticks(1);
    CHECK(b.controller.drive(0) > 0);
    b.hello(SPEC_HASH + 1);  // a host from another spec takes over: refused, and the blowers stop
    CHECK(!b.controller.session_open());
    CHECK_EQ(b.controller.drive(0), 0);
    CHECK_EQ(b.controller.setpoint_pa(0), 0);
}

TEST(ping_is_answered_with_the_host_timestamp) {
    Bench b;
    b.ticks(50);
    uint8_t p[4];
    put_u32(p, 0xCAFEF00D);
    b.command(MSG_PING, p, 4);
    Pong pong;
    decode(pong, b.last(MSG_PONG)->payload.data());
    CHECK_EQ(pong.host_time_ms, 0xCAFEF00D);
    CHECK_EQ(pong.board_time_ms, 100);
}

TEST(setpoints_are_absolute_validated_and_all_or_nothing) {
    Bench b;
    b.hello();
    CHECK_EQ(b.reply_status(b.setpoints(1000, 2000, 0)), STATUS_OK);
    CHECK_EQ(b.reply_status(b.setpoints(1500, -1, 0)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.setpoints(1500, 0, DEFAULT_MAX_PRESSURE_PA + 1)), STATUS_BAD_VALUE);
    CHECK_EQ(b.controller.setpoint_pa(0), 1000);
    CHECK_EQ(b.controller.setpoint_pa(1), 2000);
    uint8_t seq = b.setpoints(1500, 0, 0);
    b.feed(frame_of(MSG_SET_SETPOINTS, seq, 0, 0));  // wrong length: dropped, not acted on
    CHECK_EQ(b.controller.setpoint_pa(0), 1500);
    CHECK_EQ(b.controller.chamber_state(1), CHAMBER_STATE_OFF);
}

TEST(telemetry_streams_at_the_configured_period) {
    Bench b;
    b.ticks(500);
    CHECK_EQ(b.count(MSG_TELEMETRY), 0);  // no session, no stream
    b.hello();
    b.config(20, 10000);
    b.ticks(TICK_HZ);
    CHECK_EQ(b.count(MSG_TELEMETRY), 50);
    CHECK_EQ(b.reply_status(b.config(100, 10000)), STATUS_OK);
    b.ticks(TICK_HZ);
    CHECK_EQ(b.count(MSG_TELEMETRY), 60);
    CHECK_EQ(b.reply_status(b.config(5, 500)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.config(20, 20000)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.config(0, 10000)), STATUS_OK);
    b.ticks(TICK_HZ);
    CHECK_EQ(b.count(MSG_TELEMETRY), 60);
}

TEST(dropped_frames_are_counted_in_telemetry) {
    Bench b;
    b.hello();
    std::vector<uint8_t> bad = frame_of(MSG_VENT, 3, 0, 0);
    bad[1] ^= 0x40;
    b.feed(bad);
    b.feed(std::vector<uint8_t>(200, 0x55));
    b.feed(std::vector<uint8_t>(1, 0x00));
    b.transport_full = true;
    b.ticks(10);
    b.transport_full = false;
    b.ticks(10);
    Telemetry t;
    decode(t, b.last(MSG_TELEMETRY)->payload.data());
    CHECK_EQ(t.rx_bad_crc, 1);
    CHECK_EQ(t.rx_overflow, 1);
    CHECK_EQ(t.tx_dropped, 1);
}

TEST(over_pressure_latches_stops_every_blower_and_clears_only_on_command) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.setpoints(2000, 1000, 1000);
    b.ticks(5);
    CHECK(b.controller.drive(0) > 0 && b.controller.drive(1) > 0);
    b.set_pressure(1, 4100);  // above the default 4 kPa limit
    b.ticks(1);
    check_all_off(b);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_OVERPRESSURE_1);
    Fault fault;
    decode(fault, b.last(MSG_FAULT)->payload.data());
    CHECK_EQ(fault.fault_bit, FAULT_OVERPRESSURE_1);
    CHECK_NEAR(fault.pressure_pa[1], 4100, 54.3);
    CHECK_EQ(b.count(MSG_FAULT), 1);

    b.ticks(50);
    CHECK_EQ(b.count(MSG_FAULT), 1);  // reported once
    CHECK_EQ(b.reply_status(b.setpoints(1000, 0, 0)), STATUS_FAULT_LATCHED);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_FAULT_ACTIVE);
    b.set_pressure(1, 0);
    b.ticks(50);
    check_all_off(b);  // still latched: the cause is gone but nobody cleared it
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
    CHECK_EQ(b.controller.fault_flags(), 0);
    CHECK_EQ(b.controller.chamber_state(0), CHAMBER_STATE_OFF);
    CHECK_EQ(b.reply_status(b.setpoints(1000, 0, 0)), STATUS_OK);
    b.ticks(1);
    CHECK(b.controller.drive(0) > 0);
}

TEST(over_pressure_limit_is_clamped_to_the_ceiling) {
    Bench b;
    b.boot();
    CHECK_EQ(b.controller.zero_source(2), ZERO_SOURCE_BOOT);
    b.hello();
    bool ack = false;
    CHECK_EQ(b.reply_status(b.set_pid(2, 2, 3, 0, 30000, 65535), &ack), STATUS_CLAMPED);
    CHECK(ack);
    CHECK_EQ(b.controller.max_pressure_pa(2), PRESSURE_CEILING_PA);
    b.set_pressure(2, PRESSURE_CEILING_PA - 60);
    b.ticks(3);
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.set_pressure(2, PRESSURE_CEILING_PA + 60);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_OVERPRESSURE_2);
}

TEST(set_pid_checks_its_fields) {
    Bench b;
    b.hello();
    CHECK_EQ(b.reply_status(b.set_pid(3, 2, 3, 0, 3000, 65535)), STATUS_BAD_CHAMBER);
    CHECK_EQ(b.reply_status(b.set_pid(0, -2, 3, 0, 3000, 65535)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.set_pid(0, 2, NAN, 0, 3000, 65535)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.set_pid(0, 2, 3, 0, 0, 65535)), STATUS_BAD_VALUE);
    b.setpoints(2500, 0, 0);
    CHECK_EQ(b.reply_status(b.set_pid(0, 2, 3, 0, 2000, 65535)), STATUS_BAD_VALUE);  // below the setpoint
    CHECK_EQ(b.reply_status(b.set_pid(0, 4, 1, 0.01f, 3000, 30000)), STATUS_OK);
    CHECK_NEAR(b.controller.pid(0).gains().kp_per_kpa, 4, 0);
    CHECK_EQ(b.controller.max_pressure_pa(0), 3000);
}

TEST(sensor_out_of_range_latches_after_five_ticks_in_a_row) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.setpoints(1000, 1000, 1000);
    b.ticks(3);
    b.counts[0] = 5;  // broken wire: 0.02 V
    b.ticks(SENSOR_BAD_TICKS - 1);
    CHECK_EQ(b.controller.fault_flags(), 0);
    CHECK_EQ(b.controller.drive(0), 0);  // a suspect reading never drives its blower
    CHECK(b.controller.drive(1) > 0);
    b.counts[0] = 512;  // one good tick restarts the count
    b.ticks(1);
    b.counts[0] = 1020;  // rail high: 4.98 V, also an over-pressure reading, which must not be reported as such
    b.ticks(SENSOR_BAD_TICKS - 1);
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_SENSOR_0);
    check_all_off(b);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_FAULT_ACTIVE);
    b.counts[0] = 512;
    b.ticks(1);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
}

TEST(dead_host_deadline_trips_and_pings_keep_the_link_alive) {
    Bench b;
    b.ticks(1000);
    CHECK_EQ(b.controller.fault_flags(), 0);  // no session: nothing to guard
    b.hello();
    b.setpoints(1000, 0, 0);
    b.set_pressure(0, 950);  // close to the setpoint: a reading stuck far below it would be a leak
    uint8_t p[4] = {0, 0, 0, 0};
    for (int i = 0; i < 20; ++i) {
        b.ticks(200);  // 400 ms
        b.command(MSG_PING, p, 4);
    }
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.ticks(DEFAULT_HOST_DEADLINE_MS / TICK_MS);  // exactly the deadline: not yet
    CHECK_EQ(b.controller.fault_flags(), 0);
    CHECK(b.controller.drive(0) > 0);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_DEAD_HOST);
    check_all_off(b);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
    b.config(20, 100);
    b.ticks(50);
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_DEAD_HOST);
}

TEST(garbage_does_not_count_as_a_sign_of_life) {
    Bench b;
    b.hello();
    for (int i = 0; i < 10; ++i) {
        b.ticks(100);
        b.feed(std::vector<uint8_t>(30, 0x11));
        b.feed(std::vector<uint8_t>(1, 0x00));
    }
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_DEAD_HOST);
}

TEST(watchdog_reset_is_latched_and_reported_at_hello) {
    Bench b(RESET_CAUSE_WATCHDOG);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_WATCHDOG_RESET);
    CHECK_EQ(b.count(MSG_FAULT), 1);  // through the one fault path, FAULT frame included
    CHECK_EQ(b.last(MSG_FAULT)->payload[4], FAULT_WATCHDOG_RESET);
    b.hello();
    HelloReply reply;
    decode(reply, b.last(MSG_HELLO_REPLY)->payload.data());
    CHECK_EQ(reply.reset_cause, RESET_CAUSE_WATCHDOG);
    CHECK_EQ(reply.fault_flags, 1 << FAULT_WATCHDOG_RESET);
    CHECK_EQ(b.reply_status(b.setpoints(1000, 0, 0)), STATUS_FAULT_LATCHED);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
    CHECK_EQ(b.reply_status(b.setpoints(1000, 0, 0)), STATUS_OK);
}

TEST(vent_stops_every_blower_at_once_even_without_a_session) {
    Bench fresh;
    bool ack = false;
    CHECK_EQ(fresh.reply_status(fresh.simple(MSG_VENT), &ack), STATUS_OK);
    CHECK(ack);
    Bench b;
    b.hello();
    b.setpoints(1000, 2000, 3000);
    b.ticks(2);
    CHECK(b.controller.drive(2) > 0);
    b.simple(MSG_VENT);
    for (uint8_t c = 0; c < CHAMBERS; ++c) {
        CHECK_EQ(b.controller.drive(c), 0);  // before the next tick
        CHECK_EQ(b.controller.setpoint_pa(c), 0);
    }
    CHECK_EQ(b.controller.fault_flags(), 0);
}

TEST(zero_calibration_measures_offsets_and_refuses_implausible_ones) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.setpoints(1000, 0, 0);
    CHECK_EQ(b.reply_status(b.simple(MSG_ZERO_SENSORS)), STATUS_NOT_VENTED);
    b.simple(MSG_VENT);
    b.counts[0] = 520;  // +8 counts of offset
    b.counts[1] = 505;
    b.ticks(1);
    CHECK_EQ(b.reply_status(b.simple(MSG_ZERO_SENSORS)), STATUS_NOT_SETTLED);
    b.ticks(ZERO_SETTLE_TICKS - 1);
    CHECK_EQ(b.reply_status(b.simple(MSG_ZERO_SENSORS)), STATUS_NOT_SETTLED);  // one tick short
    b.ticks(1);
    uint8_t seq = b.simple(MSG_ZERO_SENSORS);
    CHECK_EQ(b.reply_status(seq), -1);  // the answer comes when it is done
    b.ticks(1);
    CHECK_EQ(b.controller.chamber_state(0), CHAMBER_STATE_ZEROING);
    CHECK_EQ(b.reply_status(b.setpoints(1000, 0, 0)), STATUS_BUSY);
    b.feed(frame_of(MSG_ZERO_SENSORS, seq, 0, 0));  // a retransmission while it runs: no second answer
    b.ticks(ZERO_TICKS - 1);
    CHECK_EQ(b.reply_status(seq), STATUS_OK);
    CHECK_EQ(b.count(MSG_ACK) + b.count(MSG_NACK), 8);
    CHECK_EQ(b.controller.zero_x16(0), 520 * 16);
    CHECK_EQ(b.controller.zero_x16(1), 505 * 16);
    CHECK_EQ(b.controller.zero_source(0), ZERO_SOURCE_HOST);
    b.ticks(1);
    CHECK_EQ(b.controller.pressure_pa(0), 0);
    CHECK_EQ(b.controller.pressure_pa(1), 0);
    b.counts[2] = 512 + 60;  // 3.3 kPa of offset: not a vented sensor
    b.ticks(ZERO_SETTLE_TICKS + 1);
    seq = b.simple(MSG_ZERO_SENSORS);
    b.ticks(ZERO_TICKS);
    CHECK_EQ(b.reply_status(seq), STATUS_ZERO_OUT_OF_RANGE);
    CHECK_EQ(b.controller.zero_x16(0), 520 * 16);  // all or nothing
    CHECK_EQ(b.controller.zero_x16(2), NOMINAL_ZERO_X16);
    // A reading that moves during the measurement ends it: NOT_SETTLED, nothing changed.
    b.counts[2] = 512;
    b.ticks(ZERO_SETTLE_TICKS + 1);
    seq = b.simple(MSG_ZERO_SENSORS);
    b.ticks(10);
    b.counts[1] = 510;
    b.ticks(ZERO_TICKS);
    CHECK_EQ(b.reply_status(seq), STATUS_NOT_SETTLED);
    CHECK_EQ(b.controller.zero_x16(1), 505 * 16);
}

TEST(test_hang_needs_its_magic_and_is_acknowledged_first) {
    Bench b;
    b.hello();
    uint8_t p[4];
    put_u32(p, 0x12345678);
    CHECK_EQ(b.reply_status(b.command(MSG_TEST_HANG, p, 4)), STATUS_BAD_MAGIC);
    CHECK(!b.controller.hang_requested());
    b.setpoints(1000, 0, 0);
    b.ticks(1);
    put_u32(p, TEST_HANG_MAGIC);
    CHECK_EQ(b.reply_status(b.command(MSG_TEST_HANG, p, 4)), STATUS_OK);
    CHECK(b.controller.hang_requested());
    CHECK_EQ(b.controller.drive(0), 0);
}

TEST(closed_loop_through_the_controller_reaches_the_setpoints) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    plant::Chamber chambers[CHAMBERS];
    chambers[1].compliance_m3_per_pa = 4e-9;  // a softer chamber
    b.setpoints(2000, 1500, 0);
    for (int tick = 0; tick < 3 * TICK_HZ; ++tick) {
        for (uint8_t c = 0; c < CHAMBERS; ++c) {
            for (int k = 0; k < 10; ++k) chambers[c].advance(b.controller.drive(c) / 65535.0, 1.0 / (10 * TICK_HZ));
            b.set_pressure(c, chambers[c].pressure_pa);
        }
        b.ticks(1);
    }
    Telemetry t;
    decode(t, b.last(MSG_TELEMETRY)->payload.data());
    CHECK_NEAR(t.pressure_pa[0], 2000, 54.3);
    CHECK_NEAR(t.pressure_pa[1], 1500, 54.3);
    CHECK_NEAR(chambers[0].pressure_pa, 2000, 60);
    CHECK_EQ(t.drive[2], 0);
    CHECK_EQ(t.state[0], CHAMBER_STATE_REGULATING);
    CHECK_EQ(t.state[2], CHAMBER_STATE_OFF);
    CHECK_EQ(t.fault_flags, 0);
}

// ---- leak: a chamber that cannot reach or hold its setpoint ------------------------------------------

// The bench and one plant per chamber in closed loop, 10 plant steps per tick.
struct ClosedLoop {
    Bench bench;
    plant::Chamber chambers[CHAMBERS];
    int tick = 0;
    int starved_run = 0;      // ticks in a row seen from outside: full drive and > LEAK_MIN_ERROR_PA below
    int longest_starved = 0;  // the longest such run

    ClosedLoop() {
        bench.hello();
        bench.config(20, 10000);
    }
    // Run up to n ticks; stop after the tick at which a new fault latched. Returns the ticks run.
    int run(int n) {
        uint16_t faults_before = bench.controller.fault_flags();
        for (int k = 0; k < n; ++k) {
            for (uint8_t c = 0; c < CHAMBERS; ++c) {
                for (int s = 0; s < 10; ++s)
                    chambers[c].advance(bench.controller.drive(c) / 65535.0, 1.0 / (10 * TICK_HZ));
                bench.set_pressure(c, chambers[c].pressure_pa);
            }
            // the drive applied over the tick that ends now, and the reading the tick takes
            bool at_ceiling[CHAMBERS];
            int16_t setpoint_pa[CHAMBERS];
            for (uint8_t c = 0; c < CHAMBERS; ++c) {
                at_ceiling[c] = bench.controller.drive(c) == bench.controller.pid(c).gains().max_drive;
                setpoint_pa[c] = bench.controller.setpoint_pa(c);
            }
            bench.ticks(1);
            ++tick;
            bool starved = false;
            for (uint8_t c = 0; c < CHAMBERS; ++c) {
                starved |= setpoint_pa[c] > 0 && at_ceiling[c] &&
                           setpoint_pa[c] - bench.controller.pressure_pa(c) > LEAK_MIN_ERROR_PA;
            }
            starved_run = starved ? starved_run + 1 : 0;
            longest_starved = starved_run > longest_starved ? starved_run : longest_starved;
            if (bench.controller.fault_flags() != faults_before) return k + 1;
        }
        return n;
    }
};

// Extra leak of the plant's chamber in ml/s per kPa (the plant's own back-leak is 0.83 ml/s/kPa).
static void add_leak(plant::Chamber& chamber, double ml_per_s_per_kpa) { chamber.leak_m3_s_per_pa += ml_per_s_per_kpa * 1e-9; }

TEST(leak_is_not_tripped_by_a_normal_step_to_3kpa) {
    // Independent of the firmware's own count: the loop measures from outside how long the blower sat at full
    // drive with the chamber far below its setpoint. The step must really saturate (else the test proves
    // nothing), and for less than the limit.
    ClosedLoop loop;
    loop.bench.setpoints(3000, 3000, 0);
    loop.run(6 * TICK_HZ);
    printf("     0 -> 3 kPa: blower at full drive, > %d Pa below the setpoint, for %.3f s (limit %.1f s)\n",
           LEAK_MIN_ERROR_PA, (double)loop.longest_starved / TICK_HZ, (double)LEAK_TICKS / TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 0);
    CHECK(loop.longest_starved > TICK_HZ / 2);
    CHECK(loop.longest_starved < LEAK_TICKS);
    CHECK_NEAR(loop.chambers[0].pressure_pa, 3000, 60);
}

TEST(leak_that_the_pid_can_outpump_is_compensated_without_a_latch) {
    // 2 ml/s/kPa more: holding 1.5 kPa takes about 4.3 ml/s of the 7 ml/s the blower gives at full drive there.
    ClosedLoop loop;
    loop.bench.setpoints(1500, 1500, 1500);
    loop.run(2 * TICK_HZ);
    add_leak(loop.chambers[2], 2.0);
    loop.run(8 * TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 0);
    CHECK_NEAR(loop.chambers[2].pressure_pa, 1500, 60);
    CHECK(loop.bench.controller.drive(2) > 0.45 * 65535 && loop.bench.controller.drive(2) < 65535);
}

TEST(leak_opening_under_a_held_pressure_latches_implausible_at_once) {
    // The reading falls under full drive and never rises again: the blower cannot raise it, which is the
    // plausibility rule's case (it does not wait for the leak rule's 2 s).
    ClosedLoop loop;
    loop.bench.setpoints(1500, 1500, 1500);
    loop.run(2 * TICK_HZ);
    add_leak(loop.chambers[2], 10.0);
    int ticks = loop.run(2 * TICK_HZ);
    printf("     severe leak opening at 1.5 kPa: IMPLAUSIBLE_2 latched %.3f s after it opened\n", (double)ticks / TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_IMPLAUSIBLE_2);
    CHECK(ticks >= PLAUSIBLE_TICKS && ticks <= PLAUSIBLE_TICKS + TICK_HZ / 10);
}

TEST(leak_the_blower_cannot_overcome_latches_through_the_one_fault_path) {
    // 10 ml/s/kPa more, there before the step: at full drive the chamber rises, but only to about 0.7 kPa of
    // its 1.5 kPa (the reading responds, so this is the leak rule's case).
    ClosedLoop loop;
    add_leak(loop.chambers[2], 10.0);
    loop.bench.setpoints(1500, 1500, 1500);
    int ticks = loop.run(6 * TICK_HZ);
    printf("     severe leak: LEAK_2 latched %.3f s after the step\n", (double)ticks / TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_LEAK_2);
    // starved from the first tick at full drive (the tick after the step)
    CHECK(ticks >= LEAK_TICKS && ticks <= LEAK_TICKS + 2);
    CHECK_EQ(loop.starved_run, LEAK_TICKS);  // seen from outside: exactly LEAK_TICKS starved ticks in a row
    check_all_off(loop.bench);
    Fault fault;
    decode(fault, loop.bench.last(MSG_FAULT)->payload.data());
    CHECK_EQ(fault.fault_bit, FAULT_LEAK_2);
    CHECK_EQ(fault.fault_flags, 1 << FAULT_LEAK_2);
    CHECK(fault.pressure_pa[2] < 1500 - LEAK_MIN_ERROR_PA);
    CHECK_NEAR(fault.pressure_pa[0], 1500, 60);
    Telemetry telemetry;
    loop.run(TICK_HZ / 10);  // the plants vent, the latch holds
    decode(telemetry, loop.bench.last(MSG_TELEMETRY)->payload.data());
    CHECK_EQ(telemetry.fault_flags, 1 << FAULT_LEAK_2);
    CHECK_EQ(telemetry.state[0], CHAMBER_STATE_FAULT);
}

TEST(leak_stays_latched_until_cleared_and_trips_again_if_it_persists) {
    ClosedLoop loop;
    add_leak(loop.chambers[0], 10.0);
    loop.bench.setpoints(1500, 0, 0);
    loop.run(3 * TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_LEAK_0);
    loop.run(5 * TICK_HZ);  // the chambers deflate; nothing clears the latch by itself
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_LEAK_0);
    check_all_off(loop.bench);
    CHECK(loop.chambers[0].pressure_pa < 50);
    CHECK_EQ(loop.bench.reply_status(loop.bench.setpoints(1500, 0, 0)), STATUS_FAULT_LATCHED);
    CHECK_EQ(loop.bench.count(MSG_FAULT), 1);
    // With the blowers off no chamber can be starved: a leak leaves no present cause, as a dead host does.
    // Another fault's present cause still refuses the clear, which then keeps LEAK_0 latched too.
    loop.bench.counts[1] = 5;
    loop.bench.ticks(SENSOR_BAD_TICKS);
    CHECK_EQ(loop.bench.reply_status(loop.bench.simple(MSG_CLEAR_FAULT)), STATUS_FAULT_ACTIVE);
    CHECK_EQ(loop.bench.controller.fault_flags(), (1 << FAULT_LEAK_0) | (1 << FAULT_SENSOR_1));
    loop.bench.counts[1] = 512;
    loop.bench.ticks(1);
    CHECK_EQ(loop.bench.reply_status(loop.bench.simple(MSG_CLEAR_FAULT)), STATUS_OK);
    CHECK_EQ(loop.bench.controller.fault_flags(), 0);
    // The leak is still there: re-inflating trips it again, after the full limit (the count started over).
    CHECK_EQ(loop.bench.reply_status(loop.bench.setpoints(1500, 0, 0)), STATUS_OK);
    int ticks = loop.run(4 * TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_LEAK_0);
    CHECK(ticks >= LEAK_TICKS && ticks <= LEAK_TICKS + TICK_HZ / 2);
    CHECK_EQ(loop.bench.count(MSG_FAULT), 3);  // LEAK_0, SENSOR_1, LEAK_0 again
}

TEST(leak_count_restarts_when_the_chamber_gets_close_or_the_drive_leaves_its_ceiling) {
    // Driven by hand: the reading is held far below the setpoint, the blower saturates.
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.setpoints(2000, 0, 0);
    b.set_pressure(0, 800);
    b.ticks(2);
    b.set_pressure(0, 1000);  // the reading responds to the blower: not a sensor that misses its chamber
    b.ticks(LEAK_TICKS - 2);  // the first tick's drive was 0 (not yet at the ceiling): one short of the limit
    CHECK_EQ(b.controller.fault_flags(), 0);
    CHECK_EQ(b.controller.drive(0), 65535);
    b.set_pressure(0, 2000 - LEAK_MIN_ERROR_PA + 60);  // within the threshold for one tick: drive 0.6
    b.ticks(1);
    CHECK(b.controller.drive(0) < 65535);
    b.set_pressure(0, 800);  // and the reading responds again (this tick ran on the drive below the ceiling)
    b.ticks(1);
    b.set_pressure(0, 1000);
    b.ticks(LEAK_TICKS - 1);
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_LEAK_0);
}

TEST(leak_ceiling_is_the_chambers_max_drive) {
    // A drive ceiling of 0.3 cannot hold 3 kPa on the plant (it needs about 0.45): starved at 0.3, not at 1.0.
    ClosedLoop loop;
    CHECK_EQ(loop.bench.reply_status(loop.bench.set_pid(1, DEFAULT_KP_PER_KPA, DEFAULT_KI_PER_KPA_S, 0, 4000,
                                                        (uint16_t)(0.3 * 65535))),
             STATUS_OK);
    loop.bench.setpoints(0, 3000, 0);
    int ticks = loop.run(8 * TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 1 << FAULT_LEAK_1);
    CHECK(ticks >= LEAK_TICKS);
    CHECK(loop.chambers[1].pressure_pa < 3000 - LEAK_MIN_ERROR_PA);
}


// ---- a zero you can trust -------------------------------------------------------------------------------

TEST(vent_then_zero_with_a_chamber_still_at_2_4kpa_is_refused_until_it_has_deflated) {
    ClosedLoop loop;
    loop.run(ZERO_SETTLE_TICKS + ZERO_TICKS);
    CHECK_EQ(loop.bench.controller.zero_source(0), ZERO_SOURCE_BOOT);
    loop.bench.setpoints(2400, 0, 0);
    loop.run(4 * TICK_HZ);
    CHECK_NEAR(loop.chambers[0].pressure_pa, 2400, 60);
    loop.bench.simple(MSG_VENT);
    CHECK_EQ(loop.bench.reply_status(loop.bench.simple(MSG_ZERO_SENSORS)), STATUS_NOT_SETTLED);
    // The host retries every 0.5 s; the zero it finally gets is taken on a chamber that has (nearly) deflated.
    int status = -1;
    double accepted_at_pa = -1;
    for (int attempt = 0; attempt < 60 && status != STATUS_OK; ++attempt) {
        loop.run(TICK_HZ / 2);
        accepted_at_pa = loop.chambers[0].pressure_pa;
        uint8_t seq = loop.bench.simple(MSG_ZERO_SENSORS);
        loop.run(ZERO_TICKS);
        status = loop.bench.reply_status(seq);
        CHECK(status == STATUS_OK || status == STATUS_NOT_SETTLED);
    }
    printf("     zero accepted with %.0f Pa left in the chamber, zero %+.2f counts from the true one\n", accepted_at_pa,
           loop.bench.controller.zero_x16(0) / 16.0 - 511.5);
    CHECK_EQ(status, STATUS_OK);
    CHECK(accepted_at_pa < 300);  // about 2 * ZERO_STABLE_PA / (1 - exp(-settle / tau)) on this plant (tau 3 s)
    CHECK_NEAR(loop.bench.controller.zero_x16(0) / 16.0, 511.5, 6);
}

TEST(setpoint_before_the_start_up_zero_cancels_it_and_a_start_up_zero_is_measured_otherwise) {
    Bench b;
    b.counts[1] = 515;
    b.ticks(ZERO_SETTLE_TICKS - 1);
    b.hello();
    b.setpoints(0, 500, 0);
    b.boot();
    CHECK_EQ(b.controller.zero_source(1), ZERO_SOURCE_NOMINAL);
    Bench quiet;
    quiet.counts[1] = 515;
    quiet.ticks(ZERO_SETTLE_TICKS + 1);  // the first tick moved the reading from nominal: the count starts there
    CHECK_EQ(quiet.controller.chamber_state(1), CHAMBER_STATE_ZEROING);
    quiet.ticks(ZERO_TICKS);
    CHECK_EQ(quiet.controller.zero_source(1), ZERO_SOURCE_BOOT);
    CHECK_EQ(quiet.controller.zero_x16(1), 515 * 16);
    CHECK_EQ(quiet.count(MSG_ACK) + quiet.count(MSG_NACK), 0);  // nobody asked: nobody is answered
    quiet.hello();
    BoardInfo info;
    decode(info, quiet.last(MSG_BOARD_INFO)->payload.data());
    CHECK_EQ(info.zero_source[1], ZERO_SOURCE_BOOT);
    CHECK_NEAR(info.zero_offset_pa[1], 3 * 16 * 3.3908, 1);
    CHECK_EQ(info.config_source, CONFIG_SOURCE_DEFAULTS);
    CHECK_EQ(info.supply_mv, 1126400 / 225);
}

// The true pressure (Pa) at which the ceiling trips on a sensor whose real zero is `true_offset` counts from
// nominal, after a start-up zero (or none: the host sent a setpoint first) and a host zero taken with
// `residual_pa` held in the chamber (a sealed chamber: worse than any real one, which deflates through its
// idle blower; the start-up zero relies on that).
static double true_trip_pa(int true_offset, bool boot_zero, double residual_pa) {
    Bench b;
    b.counts[0] = (uint16_t)(512 + true_offset);
    if (boot_zero) b.boot();
    b.hello();
    b.config(20, 10000);
    b.set_pid(0, DEFAULT_KP_PER_KPA, DEFAULT_KI_PER_KPA_S, 0, 30000, 65535);  // limit clamped to the ceiling
    if (!boot_zero) {  // the host takes over before the board measured its zero: it never will
        b.setpoints(100, 0, 0);
        b.simple(MSG_VENT);
    }
    b.counts[0] = (uint16_t)(plant::adc_counts(residual_pa) + true_offset);
    b.ticks(ZERO_SETTLE_TICKS + 1);
    b.simple(MSG_ZERO_SENSORS);
    b.ticks(ZERO_TICKS);
    if (b.controller.fault_flags() & (1 << FAULT_OVERPRESSURE_0)) return residual_pa;  // tripped already
    b.set_pressure(0, 0);
    b.ticks(1);  // vented again (the fault path needs a quiet start)
    for (double pressure_pa = 0; pressure_pa < 12000; pressure_pa += 10) {
        b.counts[0] = (uint16_t)(plant::adc_counts(pressure_pa) + true_offset);
        b.ticks(1);
        if (b.controller.fault_flags() & (1 << FAULT_OVERPRESSURE_0)) return pressure_pa;
    }
    return 1e9;
}

TEST(no_zero_the_host_can_set_moves_the_true_trip_pressure_above_the_ceiling) {
    const int offsets[] = {-45, -20, 0, 20, 45};  // counts; the datasheet allows +-46
    const double residuals_pa[] = {-2400, 0, 1200, 2400, 4000};
    double highest = 0, lowest = 1e9;
    for (int offset : offsets) {
        for (double residual : residuals_pa) {
            for (int boot = 0; boot < 2; ++boot) {
                double trip = true_trip_pa(offset, boot, residual);
                highest = trip > highest ? trip : highest;
                lowest = trip < lowest ? trip : lowest;
                if (trip > PRESSURE_CEILING_PA + 60) printf("     offset %d, boot zero %d, residual %.0f: %.0f Pa\n", offset, boot, residual, trip);
                CHECK(trip <= PRESSURE_CEILING_PA + 60);  // one ADC count of quantisation
            }
        }
    }
    printf("     ceiling %d Pa trips at a true %.0f .. %.0f Pa over every sensor offset and host zero\n",
           PRESSURE_CEILING_PA, lowest, highest);
    CHECK(lowest > PRESSURE_CEILING_PA - 5000);  // conservative, not useless
}

// ---- faults that the simulation of an ideal board could not show ------------------------------------

// One chamber (the test plant, optionally a lobe-sized one) whose sensor reads `reading_pa` whatever the
// chamber does: a tube off (0 Pa) or a sensor stuck inside its band. Returns the ticks to the latch.
static int run_with_blind_sensor(bool lobe, double reading_pa, double* true_at_latch_pa, uint16_t* faults) {
    ClosedLoop loop;
    if (lobe) {
        loop.chambers[0].air_volume_m3 = 2.1e-6;
        loop.chambers[0].compliance_m3_per_pa = 0.79e-9;
    }
    loop.bench.setpoints(2000, 0, 0);
    int tick = 0;
    for (; tick < 2 * TICK_HZ && !loop.bench.controller.fault_flags(); ++tick) {
        for (int k = 0; k < 10; ++k)
            loop.chambers[0].advance(loop.bench.controller.drive(0) / 65535.0, 1.0 / (10 * TICK_HZ));
        loop.bench.set_pressure(0, reading_pa);
        loop.bench.ticks(1);
    }
    *true_at_latch_pa = loop.chambers[0].pressure_pa;
    *faults = loop.bench.controller.fault_flags();
    return tick;
}

TEST(tube_off_or_stuck_sensor_latches_within_half_a_second_under_the_ceiling) {
    const double readings_pa[] = {0, 1000};
    for (int lobe = 0; lobe < 2; ++lobe) {
        for (double reading : readings_pa) {
            double true_pa = 0;
            uint16_t faults = 0;
            int ticks = run_with_blind_sensor(lobe, reading, &true_pa, &faults);
            printf("     %s, sensor reading %4.0f Pa: IMPLAUSIBLE_0 after %.3f s, true pressure %.0f Pa\n",
                   lobe ? "lobe" : "base", reading, (double)ticks / TICK_HZ, true_pa);
            CHECK_EQ(faults, 1 << FAULT_IMPLAUSIBLE_0);
            CHECK(ticks <= TICK_HZ / 2);
            CHECK(true_pa < PRESSURE_CEILING_PA);
        }
    }
}

TEST(implausible_latch_is_not_tripped_by_normal_steps_and_a_reading_that_responds_clears_the_count) {
    ClosedLoop loop;
    loop.chambers[1].air_volume_m3 = 2.1e-6;
    loop.chambers[1].compliance_m3_per_pa = 0.79e-9;
    loop.bench.setpoints(3000, 3000, 500);
    loop.run(4 * TICK_HZ);
    loop.bench.setpoints(1000, 500, 3000);
    loop.run(4 * TICK_HZ);
    CHECK_EQ(loop.bench.controller.fault_flags(), 0);
}

TEST(stalled_adc_is_a_bad_sample_that_drives_nothing_and_latches) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.setpoints(1000, 1000, 0);
    b.ticks(3);
    CHECK(b.controller.drive(0) > 0);
    b.conversions[0] = 0;  // the ADC chain stopped: no conversion for chamber 0
    b.ticks(1);
    CHECK_EQ(b.controller.drive(0), 0);  // the stale reading drives nothing
    CHECK(b.controller.drive(1) > 0);
    b.ticks(SENSOR_BAD_TICKS - 1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_SENSOR_0);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_FAULT_ACTIVE);
    b.conversions[0] = 4;
    b.ticks(1);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
}

TEST(kd_to_zero_clears_the_derivative_term) {
    PidGains gains = {0.2f, 0.0f, 0.5f, 65535};
    Pid pid;
    pid.init(gains);
    pid.step(2000, 0);
    CHECK_EQ(pid.step(2000, 300), 0);  // a fast rise: the derivative term pulls the output to 0
    gains.kd_s_per_kpa = 0;
    pid.set_gains(gains);
    // P alone: 0.2 /kPa * 1.7 kPa = 0.34 (a frozen derivative term would keep it at 0)
    CHECK_NEAR(pid.step(2000, 300) / 65535.0, 0.34, 1e-3);
}

TEST(retransmitted_command_is_answered_from_the_cache_and_a_stale_clear_fault_clears_nothing) {
    Bench b;
    b.boot();
    b.hello();
    b.config(20, 10000);
    b.set_pressure(1, 4100);
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_OVERPRESSURE_1);
    b.set_pressure(1, 0);
    b.ticks(1);
    uint8_t seq = b.simple(MSG_CLEAR_FAULT);
    std::vector<uint8_t> clear = frame_of(MSG_CLEAR_FAULT, seq, 0, 0);
    CHECK_EQ(b.reply_status(seq), STATUS_OK);
    b.counts[2] = 5;  // a newer fault latches while the ACK is lost
    b.ticks(SENSOR_BAD_TICKS);
    b.counts[2] = 512;
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_SENSOR_2);
    size_t replies = b.sent.size();
    b.feed(clear);  // the host retransmits the same CLEAR_FAULT
    CHECK_EQ(b.sent.size(), replies + 1);
    CHECK_EQ(b.reply_status(seq), STATUS_OK);  // the same answer again ...
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_SENSOR_2);  // ... and the newer fault stays latched
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);  // a new CLEAR_FAULT clears it
    CHECK_EQ(b.controller.fault_flags(), 0);
    // A retransmitted setpoint command is not executed twice either, but answered alike.
    seq = b.setpoints(1000, 0, 0);
    b.simple(MSG_VENT);
    b.feed(frame_of(MSG_SET_SETPOINTS, seq, 0, 0));  // wrong length: dropped
    SetSetpoints m = {{1000, 0, 0}};
    uint8_t p[SetSetpoints::PAYLOAD_SIZE];
    encode(m, p);
    b.feed(frame_of(MSG_SET_SETPOINTS, seq, p, sizeof p));
    CHECK_EQ(b.controller.setpoint_pa(0), 1000);  // VENT was the last command: this one is executed
    b.feed(frame_of(MSG_SET_SETPOINTS, seq, p, sizeof p));
    CHECK_EQ(b.reply_status(seq), STATUS_OK);
    b.hello();  // a new session: the cache is forgotten
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
}

TEST(low_supply_latches_and_is_measured_against_the_1v1_reference) {
    Bench b;
    b.hello();
    b.config(20, 10000);
    b.ticks(1);
    CHECK_EQ(b.controller.supply_mv(), 5006);  // 1126400 / 225
    b.bandgap_counts = 1126400 / 4200;  // 4.2 V
    b.ticks(SUPPLY_BAD_TICKS - 1);
    CHECK_EQ(b.controller.fault_flags(), 0);
    b.bandgap_counts = 0;  // a tick without a measurement neither counts nor restarts the count
    b.ticks(3);
    b.bandgap_counts = 1126400 / 4200;
    b.ticks(1);
    CHECK_EQ(b.controller.fault_flags(), 1 << FAULT_SUPPLY);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_FAULT_ACTIVE);
    b.bandgap_counts = 225;
    b.ticks(1);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
}

// ---- persistent settings --------------------------------------------------------------------------------

TEST(settings_survive_a_restart_and_a_bad_block_falls_back_to_the_defaults) {
    Bench first;
    first.counts[2] = 518;
    first.boot();
    first.hello();
    uint16_t generation = first.controller.settings_generation();
    CHECK(generation > 0);  // the start-up zero is worth keeping
    CHECK_EQ(first.reply_status(first.set_pid(1, 2.5f, 7.0f, 0.01f, 3000, 50000)), STATUS_OK);
    CHECK(first.controller.settings_generation() != generation);
    uint8_t block[SETTINGS_BYTES];
    first.controller.settings(block);

    Bench second(RESET_CAUSE_EXTERNAL, block);
    CHECK_EQ(second.controller.config_source(), CONFIG_SOURCE_EEPROM);
    CHECK_EQ(second.controller.zero_source(2), ZERO_SOURCE_STORED);
    CHECK_EQ(second.controller.zero_x16(2), 518 * 16);
    CHECK_EQ(second.controller.max_pressure_pa(1), 3000);
    CHECK_NEAR(second.controller.pid(1).gains().ki_per_kpa_s, 7.0, 0);
    CHECK_EQ(second.controller.pid(1).gains().max_drive, 50000);
    second.hello();
    BoardInfo info;
    decode(info, second.last(MSG_BOARD_INFO)->payload.data());
    CHECK_EQ(info.config_source, CONFIG_SOURCE_EEPROM);
    CHECK_EQ(info.zero_source[2], ZERO_SOURCE_STORED);

    uint8_t erased[SETTINGS_BYTES];
    memset(erased, 0xFF, sizeof erased);
    CHECK_EQ(Bench(RESET_CAUSE_POWER_ON, erased).controller.config_source(), CONFIG_SOURCE_DEFAULTS);
    for (uint8_t byte = 0; byte < SETTINGS_BYTES; ++byte) {
        uint8_t corrupt[SETTINGS_BYTES];
        memcpy(corrupt, block, sizeof corrupt);
        corrupt[byte] ^= 0x04;
        Bench third(RESET_CAUSE_POWER_ON, corrupt);
        CHECK_EQ(third.controller.config_source(), byte == 0 ? CONFIG_SOURCE_CORRUPT : CONFIG_SOURCE_CORRUPT);
        CHECK_EQ(third.controller.max_pressure_pa(1), DEFAULT_MAX_PRESSURE_PA);
        CHECK_EQ(third.controller.zero_source(2), ZERO_SOURCE_NOMINAL);
    }
    // A block with a good CRC but a value this firmware would never have accepted is corrupt too.
    Settings bad;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        bad.zero_x16[i] = 0;
        bad.gains[i] = DEFAULT_GAINS;
        bad.max_pressure_pa[i] = 3000;
    }
    bad.max_pressure_pa[0] = PRESSURE_CEILING_PA + 1;
    settings_encode(bad, block);
    CHECK_EQ(Bench(RESET_CAUSE_POWER_ON, block).controller.config_source(), CONFIG_SOURCE_CORRUPT);
}

// ---- status LED -------------------------------------------------------------------------------------------

TEST(status_led_blinks_the_fault_code) {
    CHECK_EQ(Controller::fault_blink_code(0), 0);
    CHECK_EQ(Controller::fault_blink_code(1 << FAULT_OVERPRESSURE_2), 1);
    CHECK_EQ(Controller::fault_blink_code((1 << FAULT_SENSOR_1) | (1 << FAULT_DEAD_HOST)), 2);
    CHECK_EQ(Controller::fault_blink_code(1 << FAULT_IMPLAUSIBLE_0), 3);
    CHECK_EQ(Controller::fault_blink_code(1 << FAULT_LEAK_1), 4);
    CHECK_EQ(Controller::fault_blink_code(1 << FAULT_SUPPLY), 7);
    Bench b;
    int lit_ms = 0;
    for (int t = 0; t < 1000; t += TICK_MS) {
        b.ticks(1);
        lit_ms += b.controller.status_led_on() ? TICK_MS : 0;
    }
    CHECK_EQ(lit_ms, 50);  // idle: a 50 ms blink each second
    b.counts[0] = 5;
    b.ticks(SENSOR_BAD_TICKS);
    lit_ms = 0;
    for (int t = 0; t < 2 * 400 + 1400; t += TICK_MS) {
        b.ticks(1);
        lit_ms += b.controller.status_led_on() ? TICK_MS : 0;
    }
    CHECK_EQ(lit_ms, 2 * 200);  // SENSOR: two 200 ms blinks per 2.2 s repeat
}

// The LED as the board shows it (time advancing a tick at a time), as runs of lit and dark: whole runs only, the
// first and the last (cut by the window) dropped. A run's sign is its level: + lit, - dark.
static std::vector<int> led_runs_ms(uint8_t code, uint32_t from_ms, uint32_t span_ms) {
    std::vector<int> runs;
    bool level = Controller::blink_code_on(code, from_ms);
    int length = 0;
    for (uint32_t t = from_ms; t < from_ms + span_ms; t += TICK_MS) {
        bool on = Controller::blink_code_on(code, t);
        if (on != level) {
            runs.push_back(level ? length : -length);
            level = on;
            length = 0;
        }
        length += TICK_MS;
    }
    if (!runs.empty()) runs.erase(runs.begin());
    return runs;
}

// Every code a person can count: within each repeat exactly `code` blinks, and between repeats a dark pause at
// least three times the longest gap between blinks (of any code) and at least 1 s, so the repeats never run
// together.
TEST(status_led_blink_codes_are_countable) {
    uint8_t largest = 0;
    for (uint8_t bit = 0; bit < 16; ++bit) {
        uint8_t code = Controller::fault_blink_code((uint16_t)(1u << bit));
        if (code > largest) largest = code;
    }
    CHECK_EQ(largest, 7);
    // A gap between blinks: any dark run shorter than the longest one of its code.
    int longest_gap_ms = 0;
    for (uint8_t code = 1; code <= largest; ++code) {
        std::vector<int> runs = led_runs_ms(code, 0, 30000);
        int longest_dark_ms = 0;
        for (size_t k = 0; k < runs.size(); ++k)
            if (-runs[k] > longest_dark_ms) longest_dark_ms = -runs[k];
        for (size_t k = 0; k < runs.size(); ++k)
            if (-runs[k] < longest_dark_ms && -runs[k] > longest_gap_ms) longest_gap_ms = -runs[k];
    }
    CHECK(longest_gap_ms >= 100);  // the blinks are told apart
    for (uint8_t code = 1; code <= largest; ++code) {
        for (uint32_t from_ms = 0; from_ms < 6000; from_ms += 1234) {
            std::vector<int> runs = led_runs_ms(code, from_ms, 30000);
            int pauses = 0, blinks = -1;  // blinks since the last pause; -1 before the first one
            for (size_t k = 0; k < runs.size(); ++k) {
                int run = runs[k];
                if (run > 0) {
                    CHECK(run >= 100 && run <= 400);  // a blink one can see and tell from the next
                    if (blinks >= 0) ++blinks;
                } else if (-run >= 3 * longest_gap_ms && -run >= 1000) {
                    if (blinks >= 0 && blinks != code) fprintf(stderr, "code %d: %d blinks a repeat\n", code, blinks);
                    if (blinks >= 0) CHECK_EQ(blinks, code);
                    blinks = 0;
                    ++pauses;
                } else {
                    if (-run > longest_gap_ms) fprintf(stderr, "code %d: a pause of %d ms\n", code, -run);
                    CHECK(-run <= longest_gap_ms);  // a gap between blinks, never something in between
                }
            }
            CHECK(pauses >= 4);  // 30 s shows several repeats
        }
    }
}

int main() { return check::run_all("firmware core unit tests"); }
