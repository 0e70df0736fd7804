// The scanner's stepper axes (0: the camera's orbit, 1: its elevation), hardware-independent: the profiles in
// steps, homing, the soft limits and the drivers' enable. The motion is planned once per window of
// WINDOW_TICKS control ticks (10 ms): for each axis, how many steps the next window makes, when its first is
// and the interval between them (the velocity is constant within a window). The AVR layer's step interrupt
// makes them; planning once a window, with no per-step work, is what fits the CPU budget (firmware/README.md).
#pragma once
#include <stdint.h>

#include "protocol_generated.h"

namespace core {

const uint8_t AXES = proto::MOTION_AXES;

// The window: WINDOW_TICKS ticks of 125 slots of 16 us (Timer0 counts at clk/256). Step times are in Q6 slots
// from the window's start: 625 slots, 40000 units.
const uint8_t WINDOW_TICKS = 5;
const uint8_t SLOTS_PER_TICK = 125;
const uint16_t WINDOW_SLOTS = (uint16_t)WINDOW_TICKS * SLOTS_PER_TICK;
const uint16_t WINDOW_Q6 = WINDOW_SLOTS * 64;
const uint16_t WINDOWS_PER_S = proto::TICK_HZ / WINDOW_TICKS;
static_assert(proto::TICK_HZ % WINDOW_TICKS == 0, "a window must be a whole fraction of a second");
const uint8_t MAX_STEPS_PER_WINDOW = (uint8_t)((proto::MOTION_MAX_STEP_RATE + WINDOWS_PER_S - 1) / WINDOWS_PER_S);

// Velocities are steps per window, accelerations steps per window per window, both in Q8.24 fixed point.
const uint32_t Q24_ONE = 1UL << 24;

// One axis's steps in a window: `count` of them, the first `first_q6` into it, then every `interval_q6`.
struct AxisSteps {
    uint8_t count;
    uint16_t first_q6;
    uint16_t interval_q6;
};

// What the stepper outputs do during the next window: DIR levels set at its start, then the steps of the one
// axis that moves (the other's count is 0).
struct StepPlan {
    uint8_t dir_high;  // bit n: axis n's DIR pin level for the whole window
    AxisSteps axis[AXES];
};

// What the AVR layer saw at the start of a tick: the home inputs' levels (bit n: axis n), whether a window
// started (the loop plans one then), and each axis's steps handed over but not made yet.
struct MotionSample {
    uint8_t home_inputs;
    bool window_start;
    uint8_t unmade_steps[AXES];
};

// An axis's configuration as MOTION_CONFIG carries it.
struct AxisConfig {
    float steps_per_rev;  // 0: the axis is absent
    uint32_t max_speed_mdeg_s;
    uint32_t max_accel_mdeg_s2;
    int32_t min_angle_mdeg;
    int32_t max_angle_mdeg;
    uint32_t home_speed_mdeg_s;
    uint8_t options;  // bits of proto::MotionOptionsBit
};

// One stepper axis. Commands return a protocol status (STATUS_OK or why not).
class Axis {
public:
    uint8_t configure(const AxisConfig& config);
    uint8_t move_to(int32_t angle_mdeg);
    uint8_t home(uint8_t method, int32_t angle_mdeg);
    // Decelerate to rest at the acceleration limit; release the driver at rest when asked.
    void stop(bool release);
    // A latched fault: no further step, the driver released now; a position that was moving is lost.
    void halt();
    // Every tick: the home input's level, and the steps handed over but not made when it was sampled.
    void sample(bool home_input_high, uint8_t unmade_steps);
    // At a window's start: the steps of the next window (count 0 when there are none).
    void plan_window(AxisSteps& out);

    const AxisConfig& config() const { return config_; }
    bool configured() const { return state_ != proto::MOTION_STATE_ABSENT; }
    uint8_t state() const { return state_; }
    // Whether plan_window() has anything to do: a move, a homing, a stop, or a release to make or count down.
    bool busy() const {
        return state_ >= proto::MOTION_STATE_MOVING ||
               (enabled_ && (release_at_rest_ || ((config_.options >> proto::MOTION_OPTIONS_RELEASE_WHEN_IDLE) & 1)));
    }
    uint8_t result() const { return result_; }
    uint8_t flags() const;
    bool switch_active() const;
    bool enabled() const { return enabled_; }
    bool dir_high() const { return (direction_ > 0) != ((config_.options >> proto::MOTION_OPTIONS_REVERSE) & 1); }
    int32_t position_steps() const { return position_; }
    int32_t position_mdeg() const { return steps_to_mdeg(position_); }
    int32_t target_mdeg() const { return state_ == proto::MOTION_STATE_IDLE ? position_mdeg() : target_mdeg_; }
    int32_t velocity_mdeg_s() const;
    bool referenced() const { return referenced_; }
    // Whether a command was taken, or the state or result changed, since clear_changed() (MOTION_STATUS is sent at
    // once then).
    bool changed() const { return changed_; }
    void clear_changed() { changed_ = false; }
    // The profile's limits and its velocity now, in Q24 steps per window (per window squared), for the tests.
    uint32_t max_velocity_q24() const { return max_velocity_q24_; }
    uint32_t max_accel_q24() const { return max_accel_q24_; }
    uint32_t velocity_q24() const { return velocity_q24_; }

private:
    enum Phase : uint8_t { ACCEL, CRUISE, DECEL, DONE };
    // A homing's phases: leave the switch it started on (and stop), search it (and stop).
    enum Homing : uint8_t { NOT_HOMING, LEAVE, LEAVE_STOP, SEEK, SEEK_STOP };

    int32_t steps_to_mdeg(int32_t steps) const;
    int32_t mdeg_to_steps(int32_t mdeg) const;
    void set_state(uint8_t state, uint8_t result);
    void enable();
    bool plan_move(int32_t target_steps);
    uint32_t profile_velocity();
    uint32_t search_travel_steps() const;
    void start_jog(int8_t direction, uint32_t goal_velocity_q24);
    uint32_t jog_velocity();
    void come_to_rest(uint8_t result);
    void advance(uint32_t velocity_q24, AxisSteps& out);

    AxisConfig config_ = {0, 0, 0, 0, 0, 0, 0};
    float mdeg_per_step_ = 0;
    uint32_t max_velocity_q24_ = 0, max_accel_q24_ = 0, home_velocity_q24_ = 0;

    uint8_t state_ = proto::MOTION_STATE_ABSENT;
    uint8_t result_ = proto::MOTION_RESULT_NONE;
    bool changed_ = false;
    bool referenced_ = true;  // the position at power-up is zero
    bool switch_homed_ = false;
    bool home_input_high_ = false;  // the home input's level at the latest tick
    bool enabled_ = false;
    bool release_at_rest_ = false;
    uint8_t idle_windows_ = 0;

    int32_t position_ = 0;        // steps, once every step handed over is made
    uint32_t fraction_q24_ = 0;   // the part of a step travelled beyond position_ (starts at half a step)
    int8_t direction_ = 1;
    uint32_t velocity_q24_ = 0;   // speed of the latest window
    int32_t target_mdeg_ = 0;

    // The move's trapezoid: accel_windows_ windows gaining accel_q24_ (or one unit more) each, cruise_windows_ at
    // cruise_q24_, then accel_windows_ - 1 windows losing as much (see plan_move); accel_extra_ is cruise_q24_ mod
    // accel_windows_, ramp_remainder_ the ramp's carried remainder.
    Phase phase_ = DONE;
    uint32_t phase_windows_left_ = 0;
    uint32_t accel_windows_ = 0, cruise_windows_ = 0;
    uint32_t accel_q24_ = 0, cruise_q24_ = 0;
    uint32_t accel_extra_ = 0, ramp_remainder_ = 0;

    // A jog towards jog_goal_q24_ at the acceleration limit (homing, stopping).
    uint32_t jog_goal_q24_ = 0;
    Homing homing_ = NOT_HOMING;
    int32_t home_angle_mdeg_ = 0;
    bool homing_found_ = false;
    uint32_t home_travel_left_ = 0;
};

// Both axes, and the step plan of the next window. One axis moves at a time: a move or a switch search is
// refused (BUSY) while the other axis is moving, homing or stopping. (Both at once would double the step
// interrupts' share of the CPU, over the budget at the top step rate; firmware/README.md has the figures.)
class Motion {
public:
    Axis& axis(uint8_t n) { return axes_[n]; }
    const Axis& axis(uint8_t n) const { return axes_[n]; }
    uint8_t move_to(uint8_t n, int32_t angle_mdeg);
    uint8_t home(uint8_t n, uint8_t method, int32_t angle_mdeg);
    void stop(bool release);
    void halt();
    // Every tick; at a window's start plan() then holds the next window's steps. Plans alternate between two
    // buffers, so that the one handed over last window stays intact while it is being made. A tick without a
    // window, or a window with no axis busy, costs a few tens of cycles.
    void tick(const MotionSample& sample);
    const StepPlan& plan() const { return plans_[current_]; }
    // Bit n: axis n's driver is enabled.
    uint8_t enabled_mask() const;
    bool any_configured() const { return axes_[0].configured() || axes_[1].configured(); }
    bool changed() const;
    void clear_changed();

private:
    void plan_window() __attribute__((noinline));

    Axis axes_[AXES];
    StepPlan plans_[2] = {{0, {{0, 0, 0}, {0, 0, 0}}}, {0, {{0, 0, 0}, {0, 0, 0}}}};
    uint8_t current_ = 0;
};

}  // namespace core
