// Native tests of the scanner's stepper axes: the trapezoid against its limits and its target, where each step
// lands in its tick, the driver's enable, stopping, halting, homing with and without a switch, and the motion
// messages through the controller (configuration, moves, limits, faults, the status and info reports).
#include <math.h>
#include <stdlib.h>

#include <vector>

#include "check.h"
#include "controller_bench.h"
#include "core/motion.h"
#include "core/reciprocal.h"

// ---- one axis ------------------------------------------------------------------------------------------------

// 360000 steps per turn: one step per millidegree, so that angles, speeds and accelerations read as steps.
static AxisConfig steps_config(uint32_t speed_steps_s, uint32_t accel_steps_s2, uint8_t options = 0,
                               uint32_t home_speed_steps_s = 0) {
    return AxisConfig{360000.0f, speed_steps_s, accel_steps_s2, -720000, 720000, home_speed_steps_s, options};
}

// Motion (axis 0 under test) with the AVR layer's stepper outputs modelled tick by tick.
struct MotionRig {
    Motion motion;
    StepperModel steppers;
    std::vector<uint32_t> velocities;  // Q24, each window's
    std::vector<AxisSteps> windows;    // axis 0's steps of each window planned

    Axis& axis() { return motion.axis(0); }
    void tick() {
        MotionSample sample = steppers.tick(motion.enabled_mask());
        motion.tick(sample);
        if (!sample.window_start) return;
        steppers.hand_over(motion.plan());
        velocities.push_back(axis().velocity_q24());
        windows.push_back(motion.plan().axis[0]);
    }
    void ticks(int n) {
        for (int i = 0; i < n; ++i) tick();
    }
    // Tick until axis 0 is at rest and its last steps are made; false if it never stops.
    bool run(long max_ticks = 20000000) {
        for (long i = 0; i < max_ticks; ++i) {
            tick();
            if (axis().state() == MOTION_STATE_IDLE) {
                ticks(2 * WINDOW_TICKS);
                return true;
            }
        }
        return false;
    }
    int32_t made() const { return steppers.pulses[0]; }
};

// The fastest continuous trapezoid over a distance, in windows (the planner works in whole windows).
static double optimal_windows(double distance, double v, double a) {
    return distance >= v * v / a ? distance / v + v / a : 2.0 * sqrt(distance / a);
}

TEST(a_move_ends_exactly_at_its_target_within_both_limits_and_near_the_fastest_time) {
    srand(7);
    int cases = 0;
    for (int trial = 0; trial < 300; ++trial) {
        uint32_t speed = 20 + rand() % (MOTION_MAX_STEP_RATE - 19);
        uint32_t accel = 20 + rand() % 100000;
        int32_t start = rand() % 20001 - 10000;
        int32_t target = trial < 20 ? start + (trial % 2 ? trial : -trial) : start + rand() % 20001 - 10000;
        if (trial % 7 == 0) target = start + (rand() % 2 ? 1 : -1);
        Axis axis;
        CHECK_EQ(axis.configure(steps_config(speed, accel)), STATUS_OK);
        CHECK_EQ(axis.home(HOME_METHOD_HERE, start), STATUS_OK);
        CHECK_EQ(axis.move_to(target), STATUS_OK);
        uint32_t previous = 0;
        int32_t made = start;
        int moving_windows = 0;
        AxisSteps out;
        for (long w = 0; w < 10000000 && axis.state() != MOTION_STATE_IDLE; ++w) {
            axis.plan_window(out);
            uint32_t v = axis.velocity_q24();
            CHECK(v <= axis.max_velocity_q24());
            uint32_t change = v > previous ? v - previous : previous - v;
            CHECK(change <= axis.max_accel_q24());
            CHECK(out.count <= MAX_STEPS_PER_WINDOW);
            previous = v;
            moving_windows += v > 0;
            made += axis.dir_high() ? out.count : -(int32_t)out.count;
        }
        CHECK_EQ(axis.state(), MOTION_STATE_IDLE);
        CHECK_EQ(axis.result(), MOTION_RESULT_REACHED);
        CHECK_EQ(axis.position_steps(), target);
        CHECK_EQ(made, target);
        CHECK_EQ(previous, 0u);
        if (target != start) {
            double v = axis.max_velocity_q24() / (double)Q24_ONE, a = axis.max_accel_q24() / (double)Q24_ONE;
            double best = optimal_windows(fabs((double)target - start), v, a);
            CHECK(moving_windows <= best + 2.0);
            CHECK(moving_windows >= best - 1.0);
            ++cases;
        }
    }
    CHECK(cases > 250);
}

TEST(the_reciprocal_table_holds_two_to_the_24_over_each_mantissa) {
    for (uint32_t m = 256; m < 512; ++m) {
        uint32_t expected = (1UL << 24) / m;
        CHECK_EQ(reciprocal_q24((uint16_t)m), expected > 65535 ? 65535 : expected);
    }
}

// The time of every step against the crossing time computed in double precision from the same velocities: within
// 2 slots plus 0.2 % of the window (the reciprocal's precision).
TEST(each_step_is_timed_where_the_travel_crosses_it) {
    const uint32_t speeds[] = {20, 99, 100, 450, 1234, MOTION_MAX_STEP_RATE};
    for (uint32_t speed : speeds) {
        Axis axis;
        CHECK_EQ(axis.configure(steps_config(speed, 6000)), STATUS_OK);
        CHECK_EQ(axis.move_to(3000), STATUS_OK);
        double fraction = 0.5;
        int steps = 0;
        AxisSteps out;
        while (axis.state() != MOTION_STATE_IDLE) {
            axis.plan_window(out);
            double v = axis.velocity_q24() / (double)Q24_ONE;
            int crossings = (int)floor(fraction + v);
            CHECK_EQ((int)out.count, crossings);
            for (int i = 0; i < crossings; ++i) {
                double expected = (1.0 - fraction + i) / v * WINDOW_Q6;
                double at = out.first_q6 + (double)i * out.interval_q6;
                CHECK_NEAR(at, expected < 64 ? 64 : expected, 2 * 64 + 0.002 * WINDOW_Q6);
            }
            if (out.count) CHECK(out.first_q6 >= 64 && out.first_q6 <= WINDOW_Q6 - 128);
            steps += crossings;
            fraction = fraction + v - crossings;
        }
        CHECK_EQ(steps, 3000);
    }
}

TEST(a_released_driver_is_enabled_at_once_and_steps_a_whole_window_later_at_the_earliest) {
    for (int offset = 0; offset < WINDOW_TICKS; ++offset) {
        MotionRig rig;
        CHECK_EQ(rig.axis().configure(steps_config(2000, 200000)), STATUS_OK);
        rig.ticks(3 * WINDOW_TICKS + offset);
        CHECK(!rig.axis().enabled());
        long command_tick = rig.steppers.ticks;  // the command arrives between this tick and the next
        CHECK_EQ(rig.axis().move_to(100), STATUS_OK);
        CHECK(rig.axis().enabled());
        CHECK(rig.run());
        double first_step_s = rig.steppers.pulse_times_s[0].front();
        CHECK(first_step_s - command_tick * 0.002 >= MOTION_ENABLE_DELAY_MS * 1e-3);
        CHECK(first_step_s - command_tick * 0.002 <= 2.0 * WINDOW_TICKS * 0.002 + 0.001);
    }
}

TEST(release_when_idle_lets_the_driver_go_after_the_idle_time_and_hold_keeps_it) {
    for (int release = 0; release < 2; ++release) {
        MotionRig rig;
        uint8_t options = release ? 1u << MOTION_OPTIONS_RELEASE_WHEN_IDLE : 0;
        CHECK_EQ(rig.axis().configure(steps_config(2000, 100000, options)), STATUS_OK);
        CHECK_EQ(rig.axis().move_to(50), STATUS_OK);
        CHECK(rig.run());
        int idle_ticks = MOTION_IDLE_RELEASE_MS / TICK_MS - 2 * WINDOW_TICKS;  // run() went on two windows
        rig.ticks(idle_ticks - 2 * WINDOW_TICKS);
        CHECK(rig.axis().enabled());
        rig.ticks(3 * WINDOW_TICKS);
        CHECK_EQ(rig.axis().enabled(), release == 0);
    }
}

TEST(stop_decelerates_at_the_limit_and_release_lets_the_driver_go_at_rest) {
    MotionRig rig;
    CHECK_EQ(rig.axis().configure(steps_config(2000, 4000)), STATUS_OK);
    CHECK_EQ(rig.axis().move_to(100000), STATUS_OK);
    rig.ticks(2000);  // past the half-second ramp
    uint32_t v = rig.axis().velocity_q24();
    CHECK_EQ(v, 20 * Q24_ONE);  // 2000 steps/s: 20 a window
    int32_t at_stop = rig.axis().position_steps();
    rig.axis().stop(true);
    CHECK_EQ(rig.axis().state(), MOTION_STATE_STOPPING);
    CHECK_EQ(rig.axis().move_to(0), STATUS_BUSY);
    size_t from = rig.velocities.size();
    CHECK(rig.run());
    uint32_t previous = v;
    for (size_t k = from; k < rig.velocities.size(); ++k) {
        CHECK(rig.velocities[k] <= previous);
        CHECK(previous - rig.velocities[k] <= rig.axis().max_accel_q24());
        previous = rig.velocities[k];
    }
    CHECK_EQ(rig.axis().result(), MOTION_RESULT_STOPPED);
    CHECK(!rig.axis().enabled());
    CHECK_EQ(rig.made(), rig.axis().position_steps());
    CHECK(rig.axis().referenced());
    // a ramp down from 2000 steps/s at 4000 steps/s^2: v^2 / 2a = 500 steps, give or take a window's travel
    CHECK_NEAR(rig.axis().position_steps() - at_stop, 500, 20);
}

TEST(a_halt_while_moving_loses_the_reference_and_at_rest_keeps_it) {
    MotionRig rig;
    CHECK_EQ(rig.axis().configure(steps_config(2000, 20000)), STATUS_OK);
    CHECK_EQ(rig.axis().move_to(200), STATUS_OK);
    CHECK(rig.run());
    rig.motion.halt();
    CHECK(rig.axis().referenced());
    CHECK(!rig.axis().enabled());
    CHECK_EQ(rig.axis().result(), MOTION_RESULT_REACHED);
    CHECK_EQ(rig.axis().move_to(0), STATUS_OK);
    rig.ticks(10 * WINDOW_TICKS);
    CHECK(rig.axis().velocity_q24() > 0);
    int32_t made = rig.made();
    rig.motion.halt();
    CHECK(!rig.axis().referenced());
    CHECK(!rig.axis().enabled());
    CHECK_EQ(rig.axis().state(), MOTION_STATE_IDLE);
    CHECK_EQ(rig.axis().result(), MOTION_RESULT_FAULT);
    rig.ticks(10 * WINDOW_TICKS);
    CHECK_EQ(rig.made(), made);  // the steps handed over are not made by a released driver
    CHECK_EQ(rig.motion.plan().axis[0].count, 0);
    CHECK_EQ(rig.axis().move_to(0), STATUS_NOT_REFERENCED);
    CHECK_EQ(rig.axis().home(HOME_METHOD_HERE, 1500), STATUS_OK);
    CHECK(rig.axis().referenced());
    CHECK_EQ(rig.axis().position_steps(), 1500);
    CHECK_EQ(rig.axis().move_to(1400), STATUS_OK);
}

// ---- homing ----------------------------------------------------------------------------------------------------

static const uint8_t SWITCH_BELOW = (1u << MOTION_OPTIONS_HOME_SWITCH);
static const uint8_t SWITCH_ABOVE = (1u << MOTION_OPTIONS_HOME_SWITCH) | (1u << MOTION_OPTIONS_HOME_POSITIVE);

// Home against a switch whose edge is at made position `edge`, starting at made position `start` (which the axis
// also believes it is at); the switch's edge is called `home_mdeg`.
static void home_against(MotionRig& rig, uint32_t home_speed, int32_t start, int32_t edge, bool below, int32_t home_mdeg) {
    CHECK_EQ(rig.axis().configure(steps_config(2500, 40000, below ? SWITCH_BELOW : SWITCH_ABOVE, home_speed)), STATUS_OK);
    rig.steppers.switches[0] = StepperModel::Switch{true, edge, below};
    rig.steppers.pulses[0] = start;
    CHECK_EQ(rig.axis().home(HOME_METHOD_HERE, start), STATUS_OK);
    rig.tick();  // the switch is sampled before the search starts
    CHECK_EQ(rig.axis().home(HOME_METHOD_SWITCH, home_mdeg), STATUS_OK);
    CHECK_EQ(rig.axis().state(), MOTION_STATE_HOMING);
    CHECK(rig.run());
}

TEST(homing_by_switch_finds_its_edge_from_either_side_to_within_a_tick_of_travel) {
    const uint32_t home_speeds[] = {100, 500, 2000};
    for (uint32_t home_speed : home_speeds) {
        for (int below = 0; below < 2; ++below) {
            for (int on_switch = 0; on_switch < 2; ++on_switch) {
                MotionRig rig;
                int32_t edge = -30000;
                int32_t start = below ? (on_switch ? edge - 2000 : 40000) : (on_switch ? edge + 2000 : -90000);
                home_against(rig, home_speed, start, edge, below, -185000);
                CHECK_EQ(rig.axis().result(), MOTION_RESULT_HOMED);
                CHECK(rig.axis().referenced());
                CHECK(rig.axis().flags() & (1u << MOTION_FLAGS_SWITCH_HOMED));
                // the axis's position minus the made position is the switch's angle minus its edge, to within the
                // steps of the tick (2 ms) in which the switch was first seen
                int32_t offset = rig.axis().position_steps() - rig.made();
                int32_t steps_per_tick = (int32_t)(home_speed / TICK_HZ) + 1;
                CHECK(abs(offset - (-185000 - edge)) <= steps_per_tick);
                CHECK(rig.axis().flags() & (1u << MOTION_FLAGS_SWITCH_ACTIVE));
            }
        }
    }
}

TEST(homing_gives_up_after_its_search_travel_and_keeps_the_old_reference) {
    MotionRig rig;
    CHECK_EQ(rig.axis().configure(AxisConfig{360000.0f, 2500, 40000, -1000, 9000, 2000, SWITCH_BELOW}), STATUS_OK);
    CHECK_EQ(rig.axis().home(HOME_METHOD_SWITCH, 0), STATUS_OK);
    CHECK(rig.run());
    CHECK_EQ(rig.axis().result(), MOTION_RESULT_SWITCH_NOT_FOUND);
    CHECK(rig.axis().referenced());
    CHECK(!(rig.axis().flags() & (1u << MOTION_FLAGS_SWITCH_HOMED)));
    CHECK_EQ(rig.made(), rig.axis().position_steps());
    // 110 % of the 10000-step soft range, plus the ramp down from the home speed
    CHECK(rig.made() <= -11000 && rig.made() >= -11000 - 200);
    // a switch that never lets go (a broken wire reads active): leaving it gives up too, and nothing is homed
    MotionRig stuck;
    CHECK_EQ(stuck.axis().configure(AxisConfig{360000.0f, 2500, 40000, -1000, 9000, 2000, SWITCH_BELOW}), STATUS_OK);
    stuck.steppers.switches[0] = StepperModel::Switch{true, 1000000, true};
    stuck.tick();
    CHECK_EQ(stuck.axis().home(HOME_METHOD_SWITCH, 0), STATUS_OK);
    CHECK(stuck.run());
    CHECK_EQ(stuck.axis().result(), MOTION_RESULT_SWITCH_NOT_FOUND);
    CHECK(!(stuck.axis().flags() & (1u << MOTION_FLAGS_SWITCH_HOMED)));
}

TEST(home_here_sets_the_position_without_moving_and_a_switch_needs_its_option) {
    Axis axis;
    CHECK_EQ(axis.home(HOME_METHOD_HERE, 0), STATUS_NO_AXIS);
    CHECK_EQ(axis.configure(steps_config(2000, 20000)), STATUS_OK);
    CHECK_EQ(axis.home(HOME_METHOD_HERE, -45000), STATUS_OK);
    CHECK_EQ(axis.position_steps(), -45000);
    CHECK_EQ(axis.position_mdeg(), -45000);
    CHECK_EQ(axis.result(), MOTION_RESULT_HOMED);
    CHECK(!axis.enabled());
    CHECK_EQ(axis.home(HOME_METHOD_SWITCH, 0), STATUS_BAD_VALUE);
    CHECK_EQ(axis.home(2, 0), STATUS_BAD_VALUE);
    CHECK_EQ(axis.home(HOME_METHOD_HERE, (int32_t)MOTION_ANGLE_LIMIT_MDEG + 1), STATUS_BAD_VALUE);
    CHECK_EQ(axis.position_steps(), -45000);
}

TEST(the_switch_input_reads_active_high_or_low_as_configured) {
    for (int low = 0; low < 2; ++low) {
        Axis axis;
        uint8_t options = SWITCH_BELOW | (low ? 1u << MOTION_OPTIONS_SWITCH_ACTIVE_LOW : 0);
        CHECK_EQ(axis.configure(steps_config(2000, 20000, options, 100)), STATUS_OK);
        axis.sample(true, 0);
        CHECK_EQ((axis.flags() >> MOTION_FLAGS_SWITCH_ACTIVE) & 1, low ? 0 : 1);
        axis.sample(false, 0);
        CHECK_EQ((axis.flags() >> MOTION_FLAGS_SWITCH_ACTIVE) & 1, low ? 1 : 0);
    }
}

// ---- configuration and moves -------------------------------------------------------------------------------

TEST(configuration_is_checked_before_anything_changes) {
    Axis axis;
    const AxisConfig good = {28800.0f, 30000, 60000, -190000, 190000, 5000, SWITCH_BELOW};
    AxisConfig bad[16];
    int n = 0;
    bad[n] = good, bad[n++].steps_per_rev = -1.0f;
    bad[n] = good, bad[n++].steps_per_rev = NAN;
    bad[n] = good, bad[n++].steps_per_rev = 0.5f;
    bad[n] = good, bad[n++].steps_per_rev = MOTION_MAX_STEPS_PER_REV * 1.01f;
    bad[n] = good, bad[n++].max_speed_mdeg_s = 0;
    bad[n] = good, bad[n++].max_speed_mdeg_s = 31251;  // 2500.08 steps/s at 0.08 steps/mdeg
    bad[n] = good, bad[n++].max_accel_mdeg_s2 = 0;
    bad[n] = good, bad[n++].max_accel_mdeg_s2 = 3125100;  // more than 2500 steps/s gained in one window
    bad[n] = good, bad[n++].min_angle_mdeg = 190000;
    bad[n] = good, bad[n++].min_angle_mdeg = -(int32_t)MOTION_ANGLE_LIMIT_MDEG - 1;
    bad[n] = good, bad[n++].max_angle_mdeg = (int32_t)MOTION_ANGLE_LIMIT_MDEG + 1;
    bad[n] = good, bad[n++].home_speed_mdeg_s = 0;
    bad[n] = good, bad[n++].home_speed_mdeg_s = 30001;
    bad[n] = good, bad[n++].options = 0x20;
    // one step per turn and 1 mdeg/s^2: under one Q24 unit per tick squared
    bad[n] = good, bad[n].steps_per_rev = 1.0f, bad[n].options = 0, bad[n++].max_accel_mdeg_s2 = 1;
    for (int i = 0; i < n; ++i) CHECK_EQ(axis.configure(bad[i]), STATUS_BAD_VALUE);
    CHECK_EQ(axis.state(), MOTION_STATE_ABSENT);
    CHECK_EQ(axis.configure(good), STATUS_OK);
    CHECK_EQ(axis.state(), MOTION_STATE_IDLE);
    AxisConfig fastest = good;
    fastest.max_speed_mdeg_s = 31250;  // exactly 2500 steps/s
    fastest.max_accel_mdeg_s2 = 3125000;
    CHECK_EQ(axis.configure(fastest), STATUS_OK);
    CHECK_EQ(axis.max_velocity_q24(), (uint32_t)MOTION_MAX_STEP_RATE / WINDOWS_PER_S * Q24_ONE);
    // without a switch its speed is not checked
    AxisConfig plain = good;
    plain.options = 0;
    plain.home_speed_mdeg_s = 0;
    CHECK_EQ(axis.configure(plain), STATUS_OK);
}

TEST(a_new_scale_drops_the_reference_and_the_first_configuration_keeps_the_power_up_zero) {
    MotionRig rig;
    CHECK(rig.axis().referenced());
    CHECK_EQ(rig.axis().configure(steps_config(2000, 20000)), STATUS_OK);
    CHECK(rig.axis().referenced());
    CHECK_EQ(rig.axis().configure(steps_config(2200, 30000)), STATUS_OK);  // limits only: still referenced
    CHECK(rig.axis().referenced());
    CHECK_EQ(rig.axis().configure(steps_config(2200, 30000, 1u << MOTION_OPTIONS_REVERSE)), STATUS_OK);
    CHECK(!rig.axis().referenced());
    CHECK_EQ(rig.axis().home(HOME_METHOD_HERE, 0), STATUS_OK);
    AxisConfig other = steps_config(2200, 30000, 1u << MOTION_OPTIONS_REVERSE);
    other.steps_per_rev = 180000.0f;
    CHECK_EQ(rig.axis().configure(other), STATUS_OK);
    CHECK(!rig.axis().referenced());
    // removing the axis releases it; it is absent until configured again
    CHECK_EQ(rig.axis().home(HOME_METHOD_HERE, 0), STATUS_OK);
    CHECK_EQ(rig.axis().move_to(100), STATUS_OK);
    CHECK(rig.axis().enabled());
    CHECK(rig.run());
    AxisConfig removed = other;
    removed.steps_per_rev = 0;
    CHECK_EQ(rig.axis().configure(removed), STATUS_OK);
    CHECK_EQ(rig.axis().state(), MOTION_STATE_ABSENT);
    CHECK(!rig.axis().enabled());
    CHECK_EQ(rig.axis().move_to(0), STATUS_NO_AXIS);
}

TEST(reverse_inverts_the_dir_pin_and_moves_are_refused_outside_the_limits_or_while_busy) {
    for (int reverse = 0; reverse < 2; ++reverse) {
        MotionRig rig;
        AxisConfig c = {360000.0f, 2000, 20000, -1000, 2000, 0, (uint8_t)(reverse << MOTION_OPTIONS_REVERSE)};
        CHECK_EQ(rig.axis().configure(c), STATUS_OK);
        CHECK_EQ(rig.axis().move_to(-1001), STATUS_OUT_OF_LIMITS);
        CHECK_EQ(rig.axis().move_to(2001), STATUS_OUT_OF_LIMITS);
        CHECK(!rig.axis().enabled());
        CHECK_EQ(rig.axis().move_to(2000), STATUS_OK);
        CHECK_EQ(rig.axis().dir_high(), reverse == 0);
        CHECK_EQ(rig.axis().move_to(0), STATUS_BUSY);
        CHECK_EQ(rig.axis().configure(c), STATUS_BUSY);
        CHECK_EQ(rig.axis().home(HOME_METHOD_HERE, 0), STATUS_BUSY);
        CHECK(rig.run());
        CHECK_EQ(rig.axis().position_steps(), 2000);
        CHECK_EQ(rig.made(), reverse ? -2000 : 2000);  // the driver turns the other way: REVERSE undoes the wiring
        CHECK_EQ(rig.axis().move_to(-1000), STATUS_OK);
        CHECK_EQ(rig.axis().dir_high(), reverse != 0);
        CHECK(rig.run());
        CHECK_EQ(rig.axis().position_steps(), -1000);
        // a move to where it is ends at once, without steps
        CHECK_EQ(rig.axis().move_to(-1000), STATUS_OK);
        CHECK_EQ(rig.axis().state(), MOTION_STATE_IDLE);
        CHECK_EQ(rig.axis().result(), MOTION_RESULT_REACHED);
    }
}

TEST(angles_and_steps_convert_with_the_configured_steps_per_turn) {
    Axis axis;
    CHECK_EQ(axis.configure(AxisConfig{28800.0f, 30000, 60000, -190000, 190000, 0, 0}), STATUS_OK);
    CHECK_EQ(axis.home(HOME_METHOD_HERE, 90000), STATUS_OK);
    CHECK_EQ(axis.position_steps(), 7200);
    CHECK_EQ(axis.position_mdeg(), 90000);
    CHECK_EQ(axis.home(HOME_METHOD_HERE, 12345), STATUS_OK);
    CHECK_EQ(axis.position_steps(), 988);  // 987.6 rounded
    CHECK_EQ(axis.position_mdeg(), 12350);
    CHECK_EQ(axis.target_mdeg(), 12350);
    CHECK_EQ(axis.configure(AxisConfig{12800.5f, 30000, 60000, -190000, 190000, 0, 0}), STATUS_OK);
    CHECK_EQ(axis.home(HOME_METHOD_HERE, -185000), STATUS_OK);
    CHECK_EQ(axis.position_steps(), (int32_t)lround(-185000 * 12800.5 / 360000));
}

// ---- through the controller ----------------------------------------------------------------------------------

struct MotionBench : Bench {
    // Ticks with a PING every 100 ms, as a host keeps the session alive; silent_ticks() without.
    void ticks(int n) {
        for (int i = 0; i < n; ++i) {
            if (++since_ping_ >= 50) {
                uint8_t p[Ping::PAYLOAD_SIZE] = {0, 0, 0, 0};
                feed(frame_of(MSG_PING, host_seq++, p, sizeof p));
                since_ping_ = 0;
            }
            Bench::ticks(1);
        }
    }
    void silent_ticks(int n) { Bench::ticks(n); }
    int since_ping_ = 0;
    uint8_t motion_config(uint8_t axis, float steps_per_rev, uint32_t speed, uint32_t accel, int32_t min_mdeg,
                          int32_t max_mdeg, uint32_t home_speed = 0, uint8_t options = 0) {
        MotionConfig m = {axis, steps_per_rev, speed, accel, min_mdeg, max_mdeg, home_speed, options};
        uint8_t p[MotionConfig::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_MOTION_CONFIG, p, sizeof p);
    }
    uint8_t move_to(uint8_t axis, int32_t angle_mdeg) {
        MoveTo m = {axis, angle_mdeg};
        uint8_t p[MoveTo::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_MOVE_TO, p, sizeof p);
    }
    uint8_t home(uint8_t axis, uint8_t method, int32_t angle_mdeg) {
        Home m = {axis, method, angle_mdeg};
        uint8_t p[Home::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_HOME, p, sizeof p);
    }
    uint8_t stop(uint8_t release) {
        MotionStop m = {release};
        uint8_t p[MotionStop::PAYLOAD_SIZE];
        encode(m, p);
        return command(MSG_MOTION_STOP, p, sizeof p);
    }
    MotionStatus last_status() const {
        MotionStatus status = {};
        const Sent* s = last(MSG_MOTION_STATUS);
        if (s) decode(status, s->payload.data());
        return status;
    }
    // The orbit: 28800 steps per turn (a 200-step motor, 16 microsteps, 9:1), 30 deg/s, 60 deg/s^2, +-190 deg.
    void orbit() { CHECK_EQ(reply_status(motion_config(0, 28800.0f, 30000, 60000, -190000, 190000)), STATUS_OK); }
};

TEST(motion_commands_need_a_session_a_known_axis_and_no_fault) {
    MotionBench b;
    CHECK_EQ(b.reply_status(b.move_to(0, 0)), STATUS_NO_SESSION);
    b.hello();
    CHECK_EQ(b.reply_status(b.move_to(0, 0)), STATUS_NO_AXIS);
    CHECK_EQ(b.reply_status(b.move_to(2, 0)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.home(2, HOME_METHOD_HERE, 0)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.motion_config(2, 28800.0f, 30000, 60000, -1000, 1000)), STATUS_BAD_VALUE);
    CHECK_EQ(b.reply_status(b.stop(2)), STATUS_BAD_VALUE);
    b.orbit();
    CHECK_EQ(b.reply_status(b.move_to(0, 190001)), STATUS_OUT_OF_LIMITS);
    b.set_pressure(0, 5000);  // over the 4 kPa limit: OVERPRESSURE_0 latches
    b.ticks(1);
    CHECK(b.controller.fault_flags() != 0);
    CHECK_EQ(b.reply_status(b.move_to(0, 1000)), STATUS_FAULT_LATCHED);
    CHECK_EQ(b.reply_status(b.home(0, HOME_METHOD_HERE, 0)), STATUS_FAULT_LATCHED);
    CHECK_EQ(b.reply_status(b.stop(0)), STATUS_OK);
    b.set_pressure(0, 0);
    b.ticks(1);
    CHECK_EQ(b.reply_status(b.simple(MSG_CLEAR_FAULT)), STATUS_OK);
    CHECK_EQ(b.reply_status(b.move_to(0, 1000)), STATUS_OK);
}

TEST(a_move_through_frames_makes_its_steps_and_reports_them) {
    MotionBench b;
    b.hello();
    b.orbit();
    CHECK_EQ(b.reply_status(b.move_to(0, 90000)), STATUS_OK);
    b.ticks(1);
    MotionStatus status = b.last_status();
    CHECK_EQ(status.state[0], MOTION_STATE_MOVING);
    CHECK_EQ(status.target_mdeg[0], 90000);
    CHECK_EQ(status.state[1], MOTION_STATE_ABSENT);
    b.ticks(2500);  // 90 deg at 30 deg/s with 0.5 s ramps: 3.5 s
    status = b.last_status();
    CHECK_EQ(status.state[0], MOTION_STATE_IDLE);
    CHECK_EQ(status.result[0], MOTION_RESULT_REACHED);
    CHECK_EQ(status.position_steps[0], 7200);
    CHECK_EQ(status.position_mdeg[0], 90000);
    CHECK_EQ(status.velocity_mdeg_s[0], 0);
    CHECK_EQ(status.flags[0] & (1u << MOTION_FLAGS_ENABLED | 1u << MOTION_FLAGS_REFERENCED),
             1u << MOTION_FLAGS_ENABLED | 1u << MOTION_FLAGS_REFERENCED);
    CHECK_EQ(b.steppers.pulses[0], 7200);
    CHECK_EQ(b.steppers.ignored_pulses[0], 0);
    CHECK_EQ(b.steppers.pulses[1], 0);
    CHECK_EQ(b.reply_status(b.move_to(0, -30000)), STATUS_OK);
    b.ticks(2500);
    CHECK_EQ(b.steppers.pulses[0], -2400);
    CHECK_EQ(b.last_status().position_mdeg[0], -30000);
}

// Ticks in which the board sent more than one of TELEMETRY, MOTION_STATUS and MOTION_INFO.
static int crowded_ticks(MotionBench& b, int ticks) {
    int crowded = 0;
    for (int i = 0; i < ticks; ++i) {
        size_t mark = b.sent.size();
        b.ticks(1);
        int frames = 0;
        for (size_t k = mark; k < b.sent.size(); ++k)
            frames += b.sent[k].id == MSG_TELEMETRY || b.sent[k].id == MSG_MOTION_STATUS || b.sent[k].id == MSG_MOTION_INFO;
        crowded += frames > 1;
    }
    return crowded;
}

TEST(status_streams_every_period_and_at_once_on_a_change_but_never_beside_telemetry) {
    MotionBench b;
    b.hello();
    CHECK_EQ(crowded_ticks(b, 100), 0);
    CHECK_EQ(b.count(MSG_MOTION_STATUS), 0);  // no axis: no status
    b.orbit();
    CHECK_EQ(crowded_ticks(b, 500), 0);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 1);
    // one a period (100 ms = 50 ticks), and one for the configuration
    int periodic = b.count(MSG_MOTION_STATUS);
    CHECK(periodic >= 10 && periodic <= 11);
    // the move is reported within two ticks (the next, or the one after when telemetry takes the next)
    for (int offset = 0; offset < 10; ++offset) {
        b.ticks(offset);
        int before = b.count(MSG_MOTION_STATUS);
        b.move_to(0, (offset % 2 ? -1 : 1) * 1000);
        b.ticks(2);
        CHECK_EQ(b.count(MSG_MOTION_STATUS), before + 1);
        CHECK_EQ(b.last_status().state[0], MOTION_STATE_MOVING);
        CHECK_EQ(crowded_ticks(b, 400), 0);
        CHECK_EQ(b.last_status().state[0], MOTION_STATE_IDLE);
    }
}

TEST(motion_info_follows_each_configuration_and_each_hello_for_configured_axes) {
    MotionBench b;
    b.hello();
    b.ticks(5);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 0);
    CHECK_EQ(b.reply_status(b.motion_config(1, 12800.5f, 10000, 20000, 0, 60000, 2000, 0x15)), STATUS_OK);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 0);  // not in the receive path: in a tick without another frame
    b.ticks(5);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 1);
    MotionInfo info;
    decode(info, b.last(MSG_MOTION_INFO)->payload.data());
    CHECK_EQ(info.axis, 1);
    CHECK_EQ(info.steps_per_rev, 12800.5f);
    CHECK_EQ(info.max_speed_mdeg_s, 10000u);
    CHECK_EQ(info.max_accel_mdeg_s2, 20000u);
    CHECK_EQ(info.min_angle_mdeg, 0);
    CHECK_EQ(info.max_angle_mdeg, 60000);
    CHECK_EQ(info.home_speed_mdeg_s, 2000u);
    CHECK_EQ(info.options, 0x15);
    // a refused configuration is not reported
    CHECK_EQ(b.reply_status(b.motion_config(0, 28800.0f, 0, 60000, -1000, 1000)), STATUS_BAD_VALUE);
    b.ticks(5);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 1);
    b.hello();
    b.ticks(5);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 2);
    CHECK_EQ(b.last(MSG_MOTION_INFO)->payload[0], 1);
}

// The board sends a configuration's MOTION_INFO once; a tick whose frame finds the transport full (the UART's ring)
// must not lose it: it stays pending and goes in a later tick (the telemetry of that tick is dropped and counted).
TEST(motion_info_that_finds_the_transport_full_is_sent_in_a_later_tick) {
    MotionBench b;
    b.hello();
    b.ticks(5);
    CHECK_EQ(b.reply_status(b.motion_config(0, 28800.0f, 30000, 60000, -190000, 190000)), STATUS_OK);
    b.transport_full = true;
    b.ticks(10);  // the configuration's MOTION_STATUS and MOTION_INFO, and a telemetry frame, find no room
    b.transport_full = false;
    CHECK_EQ(b.count(MSG_MOTION_INFO), 0);
    b.ticks(5);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 1);
    CHECK_EQ(b.last(MSG_MOTION_INFO)->payload[0], 0);
    b.ticks(50);
    CHECK_EQ(b.count(MSG_MOTION_INFO), 1);  // once
}

TEST(a_fault_during_a_move_halts_it_releases_the_driver_and_drops_the_reference) {
    MotionBench b;
    b.hello();
    b.orbit();
    b.move_to(0, 180000);
    b.ticks(500);
    CHECK(b.controller.motion_enabled_mask() == 1);
    CHECK(b.controller.step_plan().axis[0].count > 0);
    b.set_pressure(1, 5000);
    b.ticks(1);
    CHECK(b.controller.fault_flags() & (1u << FAULT_OVERPRESSURE_1));
    CHECK_EQ(b.controller.motion_enabled_mask(), 0);
    CHECK_EQ(b.controller.step_plan().axis[0].count, 0);
    int32_t at_fault = b.steppers.pulses[0];
    b.ticks(100);
    CHECK_EQ(b.steppers.pulses[0], at_fault);  // the steps handed over before the fault go to a released driver
    CHECK(b.steppers.ignored_pulses[0] > 0);
    MotionStatus status = b.last_status();
    CHECK_EQ(status.state[0], MOTION_STATE_IDLE);
    CHECK_EQ(status.result[0], MOTION_RESULT_FAULT);
    CHECK_EQ(status.flags[0] & (1u << MOTION_FLAGS_REFERENCED | 1u << MOTION_FLAGS_ENABLED), 0);
}

TEST(a_dead_host_and_a_refused_hello_halt_the_motion_too) {
    MotionBench b;
    b.hello();
    b.orbit();
    b.move_to(0, 180000);
    int deadline_ticks = DEFAULT_HOST_DEADLINE_MS / TICK_MS;
    b.silent_ticks(deadline_ticks);
    CHECK_EQ(b.controller.motion_enabled_mask(), 1);
    b.silent_ticks(2);
    CHECK(b.controller.fault_flags() & (1u << FAULT_DEAD_HOST));
    CHECK_EQ(b.controller.motion_enabled_mask(), 0);
    CHECK_EQ(b.controller.motion().axis(0).result(), MOTION_RESULT_FAULT);

    MotionBench c;
    c.hello();
    c.orbit();
    c.move_to(0, 180000);
    c.ticks(100);
    CHECK_EQ(c.controller.motion_enabled_mask(), 1);
    c.hello(SPEC_HASH ^ 1);
    CHECK_EQ(c.controller.motion_enabled_mask(), 0);
    CHECK_EQ(c.controller.step_plan().axis[0].count, 0);
    c.ticks(10);
    CHECK_EQ(c.controller.motion().axis(0).state(), MOTION_STATE_IDLE);
}

TEST(motion_stop_through_frames_decelerates_and_can_release) {
    MotionBench b;
    b.hello();
    b.orbit();
    b.move_to(0, 180000);
    b.ticks(1000);
    CHECK_EQ(b.reply_status(b.stop(1)), STATUS_OK);
    b.ticks(1);
    CHECK_EQ(b.last_status().state[0], MOTION_STATE_STOPPING);
    b.ticks(300);  // from 30 deg/s at 60 deg/s^2: 0.5 s
    CHECK_EQ(b.last_status().state[0], MOTION_STATE_IDLE);
    CHECK_EQ(b.last_status().result[0], MOTION_RESULT_STOPPED);
    CHECK_EQ(b.controller.motion_enabled_mask(), 0);
    CHECK_EQ(b.steppers.pulses[0], b.controller.motion().axis(0).position_steps());
    CHECK(b.controller.motion().axis(0).referenced());
}

TEST(one_axis_moves_at_a_time_and_the_other_waits_until_it_is_at_rest) {
    MotionBench b;
    b.hello();
    CHECK_EQ(b.reply_status(b.motion_config(1, 64000.0f, 10000, 200000, -90000, 90000, 2000, 0x02)), STATUS_OK);
    b.orbit();
    CHECK_EQ(b.reply_status(b.move_to(0, 180000)), STATUS_OK);
    CHECK_EQ(b.reply_status(b.move_to(1, -90000)), STATUS_BUSY);
    CHECK_EQ(b.reply_status(b.home(1, HOME_METHOD_SWITCH, 0)), STATUS_BUSY);
    CHECK_EQ(b.reply_status(b.home(1, HOME_METHOD_HERE, 1000)), STATUS_OK);  // sets a position, moves nothing
    b.ticks(100);
    b.stop(0);
    CHECK_EQ(b.reply_status(b.move_to(1, -90000)), STATUS_BUSY);  // the orbit is still stopping
    for (int i = 0; i < 1000 && b.controller.motion().axis(0).state() != MOTION_STATE_IDLE; ++i) b.ticks(1);
    CHECK_EQ(b.reply_status(b.move_to(1, -90000)), STATUS_OK);
    CHECK_EQ(b.reply_status(b.move_to(0, 0)), STATUS_BUSY);
    b.ticks(6000);
    CHECK_EQ(b.steppers.pulses[1], -16178);  // from 1000 mdeg (178 steps) to -90 deg
    CHECK_EQ(b.steppers.pulses[0], b.controller.motion().axis(0).position_steps());
    CHECK_EQ(b.steppers.ignored_pulses[0] + b.steppers.ignored_pulses[1], 0);
}

int main() { return check::run_all("motion unit tests"); }
