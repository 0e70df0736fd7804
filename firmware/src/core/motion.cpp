#include "motion.h"

#include <math.h>

#include "reciprocal.h"

namespace core {

using namespace proto;

// A released driver is enabled when a command needs it, and the command's first steps are planned at the next
// window's start and made during the window after: a whole window after the enable at least.
static_assert(MOTION_ENABLE_DELAY_MS <= 1000 / WINDOWS_PER_S, "the enable delay must fit in one window");
static_assert(MOTION_IDLE_RELEASE_MS % (1000 / WINDOWS_PER_S) == 0 && MOTION_IDLE_RELEASE_MS / (1000 / WINDOWS_PER_S) < 256,
              "the idle release must be a whole number of windows, under 256");
static const uint8_t IDLE_RELEASE_WINDOWS = (uint8_t)(MOTION_IDLE_RELEASE_MS / (1000 / WINDOWS_PER_S));
// A move is planned in windows; with more than this (cruise, plus both ramps) its fixed-point sums could lose a
// step (plan_move). 2^22 windows are 11.6 hours.
static const uint32_t MAX_MOVE_WINDOWS = 1UL << 22;
static const uint8_t KNOWN_OPTIONS = (1u << MOTION_OPTIONS_REVERSE) | (1u << MOTION_OPTIONS_HOME_SWITCH) |
                                     (1u << MOTION_OPTIONS_SWITCH_ACTIVE_LOW) | (1u << MOTION_OPTIONS_HOME_POSITIVE) |
                                     (1u << MOTION_OPTIONS_RELEASE_WHEN_IDLE);

static bool has(uint8_t options, uint8_t bit) { return (options >> bit) & 1; }

// Steps per window (or per window squared) in Q24; the caller has bounded the value.
static uint32_t to_q24(float steps_per_window) { return (uint32_t)(steps_per_window * (float)Q24_ONE + 0.5f); }

// ---- configuration and commands ----------------------------------------------------------------------------

// Check everything first, then apply: a refused configuration changes nothing. A configured axis whose scale
// (steps per turn or direction) changes loses its reference; a new one keeps the power-up zero.
uint8_t Axis::configure(const AxisConfig& c) {
    if (state_ != MOTION_STATE_ABSENT && state_ != MOTION_STATE_IDLE) return STATUS_BUSY;
    if (!(c.steps_per_rev >= 0.0f) || c.steps_per_rev > (float)MOTION_MAX_STEPS_PER_REV) return STATUS_BAD_VALUE;
    if (c.steps_per_rev == 0.0f) {
        halt();
        config_ = c;
        set_state(MOTION_STATE_ABSENT, MOTION_RESULT_NONE);
        return STATUS_OK;
    }
    const int32_t limit = (int32_t)MOTION_ANGLE_LIMIT_MDEG;
    if (c.steps_per_rev < 1.0f || c.min_angle_mdeg < -limit || c.max_angle_mdeg > limit ||
        c.min_angle_mdeg >= c.max_angle_mdeg || (c.options & ~KNOWN_OPTIONS))
        return STATUS_BAD_VALUE;
    float steps_per_mdeg = c.steps_per_rev / 360000.0f;
    float rate_steps_s = (float)c.max_speed_mdeg_s * steps_per_mdeg;
    float accel_steps_s2 = (float)c.max_accel_mdeg_s2 * steps_per_mdeg;
    const float slack = 1.000001f;  // the float product of a rate set exactly at the limit
    if (rate_steps_s > MOTION_MAX_STEP_RATE * slack ||
        accel_steps_s2 > (float)MOTION_MAX_STEP_RATE * WINDOWS_PER_S * slack)
        return STATUS_BAD_VALUE;
    uint32_t max_velocity = to_q24(rate_steps_s / WINDOWS_PER_S);
    const uint32_t cap = (uint32_t)(((uint64_t)MOTION_MAX_STEP_RATE << 24) / WINDOWS_PER_S);
    if (max_velocity > cap) max_velocity = cap;
    uint32_t max_accel = to_q24(accel_steps_s2 / ((float)WINDOWS_PER_S * WINDOWS_PER_S));
    uint32_t home_velocity = to_q24((float)c.home_speed_mdeg_s * steps_per_mdeg / WINDOWS_PER_S);
    bool home_switch = has(c.options, MOTION_OPTIONS_HOME_SWITCH);
    if (max_velocity == 0 || max_accel == 0 ||
        (home_switch && (home_velocity == 0 || c.home_speed_mdeg_s > c.max_speed_mdeg_s)))
        return STATUS_BAD_VALUE;
    bool rescaled = configured() && (c.steps_per_rev != config_.steps_per_rev ||
                                     has(c.options ^ config_.options, MOTION_OPTIONS_REVERSE));
    config_ = c;
    mdeg_per_step_ = 360000.0f / c.steps_per_rev;
    max_velocity_q24_ = max_velocity;
    max_accel_q24_ = max_accel;
    home_velocity_q24_ = home_velocity > max_velocity ? max_velocity : home_velocity;
    if (rescaled) {
        referenced_ = false;
        switch_homed_ = false;
    }
    if (state_ == MOTION_STATE_ABSENT) set_state(MOTION_STATE_IDLE, MOTION_RESULT_NONE);
    changed_ = true;
    return STATUS_OK;
}

uint8_t Axis::move_to(int32_t angle_mdeg) {
    if (!configured()) return STATUS_NO_AXIS;
    if (state_ != MOTION_STATE_IDLE) return STATUS_BUSY;
    if (!referenced_) return STATUS_NOT_REFERENCED;
    if (angle_mdeg < config_.min_angle_mdeg || angle_mdeg > config_.max_angle_mdeg) return STATUS_OUT_OF_LIMITS;
    int32_t target = mdeg_to_steps(angle_mdeg);
    if (target != position_ && !plan_move(target)) return STATUS_BAD_VALUE;
    target_mdeg_ = angle_mdeg;
    changed_ = true;
    if (target == position_) {
        set_state(MOTION_STATE_IDLE, MOTION_RESULT_REACHED);
        return STATUS_OK;
    }
    enable();
    set_state(MOTION_STATE_MOVING, MOTION_RESULT_NONE);
    return STATUS_OK;
}

uint8_t Axis::home(uint8_t method, int32_t angle_mdeg) {
    if (!configured()) return STATUS_NO_AXIS;
    if (state_ != MOTION_STATE_IDLE) return STATUS_BUSY;
    const int32_t limit = (int32_t)MOTION_ANGLE_LIMIT_MDEG;
    if (angle_mdeg < -limit || angle_mdeg > limit) return STATUS_BAD_VALUE;
    changed_ = true;
    if (method == HOME_METHOD_HERE) {
        position_ = mdeg_to_steps(angle_mdeg);
        referenced_ = true;
        switch_homed_ = false;
        set_state(MOTION_STATE_IDLE, MOTION_RESULT_HOMED);
        return STATUS_OK;
    }
    if (method != HOME_METHOD_SWITCH || !has(config_.options, MOTION_OPTIONS_HOME_SWITCH)) return STATUS_BAD_VALUE;
    home_angle_mdeg_ = angle_mdeg;
    target_mdeg_ = angle_mdeg;
    homing_found_ = false;
    home_travel_left_ = search_travel_steps();
    int8_t search = has(config_.options, MOTION_OPTIONS_HOME_POSITIVE) ? 1 : -1;
    // Already on the switch: leave it first, so that the edge is always met in the search direction.
    bool on_switch = switch_active();
    homing_ = on_switch ? LEAVE : SEEK;
    start_jog(on_switch ? (int8_t)-search : search, home_velocity_q24_);
    enable();
    set_state(MOTION_STATE_HOMING, MOTION_RESULT_NONE);
    return STATUS_OK;
}

// The driver on (if released) for a command that moves; a release asked before is forgotten.
void Axis::enable() {
    enabled_ = true;
    release_at_rest_ = false;
    idle_windows_ = 0;
}

void Axis::stop(bool release) {
    if (state_ == MOTION_STATE_ABSENT) return;
    changed_ = true;
    release_at_rest_ = release_at_rest_ || release;
    if (state_ == MOTION_STATE_IDLE) return;
    if (velocity_q24_ == 0) return come_to_rest(MOTION_RESULT_STOPPED);  // not started yet: nothing to decelerate
    phase_ = DONE;
    homing_ = NOT_HOMING;
    jog_goal_q24_ = 0;
    set_state(MOTION_STATE_STOPPING, MOTION_RESULT_NONE);
}

void Axis::halt() {
    if (velocity_q24_ > 0) {
        // the rotor coasts once its driver is released: where it stops is unknown
        referenced_ = false;
        switch_homed_ = false;
    }
    enabled_ = false;
    velocity_q24_ = 0;
    phase_ = DONE;
    homing_ = NOT_HOMING;
    release_at_rest_ = false;
    if (state_ != MOTION_STATE_ABSENT && state_ != MOTION_STATE_IDLE) set_state(MOTION_STATE_IDLE, MOTION_RESULT_FAULT);
}

// ---- the profiles ------------------------------------------------------------------------------------------

// A trapezoid in whole windows that ends exactly at the target with both limits held. With S = accel_ticks +
// cruise_ticks and N = accel_ticks, the velocities are floor(kV / N) for k = 1..N (accelerating), V for S - N
// windows, then floor(jV / N) for j = N - 1..1 (decelerating), where V = D / S in Q24 (D the distance in steps):
// consecutive windows differ by floor(V / N) or one more, at most a_max when N >= V / a_max. The sum is V S less
// under 2N Q24 units, and V S is D less under S units, so the half step the fraction starts at makes the count
// of whole steps exactly D while S + 2N < 2^23. The smallest S with V <= v_max and such an N is
// max(D / v_max, sqrt(D / a_max)).
bool Axis::plan_move(int32_t target_steps) {
    int32_t delta = target_steps - position_;
    uint32_t distance = (uint32_t)(delta > 0 ? delta : -delta);
    float d = (float)distance;
    float ticks = fmaxf(d * Q24_ONE / max_velocity_q24_, sqrtf(d * Q24_ONE / max_accel_q24_));
    if (!(ticks < (float)MAX_MOVE_WINDOWS)) return false;
    uint32_t span = (uint32_t)ceilf(ticks);
    if (span == 0) span = 1;
    uint32_t cruise, accel_ticks;
    for (;;) {  // the float estimate may be one window short of the integer conditions
        cruise = (uint32_t)(((uint64_t)distance << 24) / span);
        accel_ticks = (cruise + max_accel_q24_ - 1) / max_accel_q24_;
        if (accel_ticks == 0) accel_ticks = 1;
        if (cruise <= max_velocity_q24_ && accel_ticks <= span) break;
        ++span;
    }
    if (span + 2 * accel_ticks > MAX_MOVE_WINDOWS) return false;
    direction_ = delta > 0 ? 1 : -1;
    cruise_q24_ = cruise;
    accel_windows_ = accel_ticks;
    accel_q24_ = cruise / accel_ticks;
    accel_extra_ = cruise % accel_ticks;
    ramp_remainder_ = 0;
    cruise_windows_ = span - accel_ticks;
    phase_ = ACCEL;
    phase_windows_left_ = accel_ticks;
    velocity_q24_ = 0;
    fraction_q24_ = Q24_ONE / 2;
    return true;
}

// The velocity of the move's next window; 0 once the trapezoid is over. floor(kV / N) = kA + floor(kr / N) with
// V = NA + r: the remainder kr mod N is carried from window to window, so that none divides.
uint32_t Axis::profile_velocity() {
    while (phase_ != DONE && phase_windows_left_ == 0) {
        if (phase_ == ACCEL) {
            phase_ = CRUISE;
            phase_windows_left_ = cruise_windows_;
        } else if (phase_ == CRUISE) {
            phase_ = DECEL;
            phase_windows_left_ = accel_windows_ - 1;
            ramp_remainder_ = 0;
        } else {
            phase_ = DONE;
        }
        velocity_q24_ = cruise_q24_;
    }
    if (phase_ == DONE) return 0;
    --phase_windows_left_;
    if (phase_ == ACCEL) {
        velocity_q24_ += accel_q24_;
        ramp_remainder_ += accel_extra_;
        if (ramp_remainder_ >= accel_windows_) {
            ramp_remainder_ -= accel_windows_;
            ++velocity_q24_;
        }
    } else if (phase_ == DECEL) {
        if (ramp_remainder_ < accel_extra_) {
            velocity_q24_ -= accel_q24_ + 1;
            ramp_remainder_ += accel_windows_ - accel_extra_;
        } else {
            velocity_q24_ -= accel_q24_;
            ramp_remainder_ -= accel_extra_;
        }
    }
    return velocity_q24_;
}

// How far a switch search (or the leaving of the switch) goes before it gives up.
uint32_t Axis::search_travel_steps() const {
    float range_steps = (float)(config_.max_angle_mdeg - config_.min_angle_mdeg) / mdeg_per_step_;
    return (uint32_t)(range_steps * MOTION_HOME_SEARCH_PERCENT / 100.0f) + 1;
}

// Start a jog from rest in a direction (homing), towards a velocity reached at the acceleration limit.
void Axis::start_jog(int8_t direction, uint32_t goal_velocity_q24) {
    direction_ = direction;
    jog_goal_q24_ = goal_velocity_q24;
    velocity_q24_ = 0;
    fraction_q24_ = Q24_ONE / 2;
}

// The jog's next velocity: one acceleration limit closer to its goal.
uint32_t Axis::jog_velocity() {
    uint32_t v = velocity_q24_;
    if (v < jog_goal_q24_) return jog_goal_q24_ - v > max_accel_q24_ ? v + max_accel_q24_ : jog_goal_q24_;
    return v - jog_goal_q24_ > max_accel_q24_ ? v - max_accel_q24_ : jog_goal_q24_;
}

// The axis comes to rest: the result is set, and the driver released if asked.
void Axis::come_to_rest(uint8_t result) {
    velocity_q24_ = 0;
    phase_ = DONE;
    homing_ = NOT_HOMING;
    idle_windows_ = 0;
    set_state(MOTION_STATE_IDLE, result);
}

// The bit length of a non-zero value (the index of its top bit, plus one).
static uint8_t bit_length(uint32_t value) { return (uint8_t)(8 * sizeof(unsigned long) - __builtin_clzl(value)); }

// Travel one window at a velocity: the whole steps it crosses, when the first is and the interval between them
// (the velocity is constant within the window). Crossing i lies (gap + i) / v of the window in, with gap the
// part of a step left to the next crossing (gap <= v when there is one). 1 / v comes from a table of 9-bit
// mantissas (reciprocal.h), good to 1/512: the last steps of a window may be up to 0.2 % of it (1.2 slots) off.
// Times are Q6 slots, 40000 to a window.
void Axis::advance(uint32_t velocity_q24, AxisSteps& out) {
    velocity_q24_ = velocity_q24;
    uint32_t start = fraction_q24_;
    uint32_t end = start + velocity_q24;
    uint8_t count = (uint8_t)(end >> 24);
    fraction_q24_ = end & (Q24_ONE - 1);
    position_ += direction_ > 0 ? (int32_t)count : -(int32_t)count;
    if (homing_ != NOT_HOMING) home_travel_left_ = home_travel_left_ > count ? home_travel_left_ - count : 0;
    out.count = count;
    out.interval_q6 = 0;
    if (!count) return;
    const uint16_t first_min_q6 = 64, last_q6 = WINDOW_Q6 - 128;  // from the first slot to the last but one
    uint32_t gap = Q24_ONE - start;
    uint32_t first_q6 = 0;
    if (velocity_q24 >= 256) {  // (under 2^-16 steps a window the step is at its very start)
        uint8_t shift = (uint8_t)(bit_length(velocity_q24) - 9);
        uint16_t mantissa = (uint16_t)((velocity_q24 + (1UL << shift >> 1)) >> shift);  // rounded: within 1/512
        uint32_t reciprocal = reciprocal_q24(mantissa > 511 ? 511 : mantissa);
        if (count == 1) {
            first_q6 = ((((gap >> shift) * reciprocal) >> 8) * (WINDOW_Q6 / 64)) >> 10;
        } else {  // at least a step a window: shift >= 16, the interval under a window
            out.interval_q6 = (uint16_t)(((uint32_t)WINDOW_Q6 * reciprocal) >> shift);
            first_q6 = ((gap >> 8) * out.interval_q6) >> 16;
        }
    }
    out.first_q6 = (uint16_t)(first_q6 < first_min_q6 ? first_min_q6 : first_q6 > last_q6 ? last_q6 : first_q6);
}

// The homing watches its switch at every tick, where the steps made so far are known exactly: at the switch's
// edge the reference is set; leaving or finding it ends the phase (the next window decelerates).
void Axis::sample(bool home_input_high, uint8_t unmade_steps) {
    home_input_high_ = home_input_high;
    if (homing_ != LEAVE && homing_ != SEEK) return;
    bool active = switch_active();
    if (homing_ == LEAVE && !active) {
        homing_ = LEAVE_STOP;
        jog_goal_q24_ = 0;
    } else if (homing_ == SEEK && active) {
        int32_t made_position = position_ - (direction_ > 0 ? (int32_t)unmade_steps : -(int32_t)unmade_steps);
        position_ += mdeg_to_steps(home_angle_mdeg_) - made_position;
        referenced_ = true;
        switch_homed_ = true;
        homing_found_ = true;
        homing_ = SEEK_STOP;
        jog_goal_q24_ = 0;
    }
}

void Axis::plan_window(AxisSteps& out) {
    out.count = 0;
    if (state_ == MOTION_STATE_IDLE) {
        // released a window after it came to rest at the earliest: the last steps handed over are made by then
        if (release_at_rest_ ||
            (has(config_.options, MOTION_OPTIONS_RELEASE_WHEN_IDLE) && ++idle_windows_ >= IDLE_RELEASE_WINDOWS)) {
            enabled_ = false;
            release_at_rest_ = false;
        }
        return;
    }
    if (state_ == MOTION_STATE_ABSENT) return;
    uint32_t velocity;
    if (state_ == MOTION_STATE_MOVING) {
        velocity = profile_velocity();
        if (velocity == 0) return come_to_rest(MOTION_RESULT_REACHED);
    } else {
        if ((homing_ == LEAVE || homing_ == SEEK) && home_travel_left_ == 0) {  // the search gives up
            homing_ = SEEK_STOP;
            jog_goal_q24_ = 0;
        }
        velocity = jog_velocity();
        if (velocity == 0 && jog_goal_q24_ == 0) {
            if (homing_ == LEAVE_STOP) {
                homing_ = SEEK;
                home_travel_left_ = search_travel_steps();
                start_jog((int8_t)-direction_, home_velocity_q24_);
                changed_ = true;
                return;
            }
            if (homing_ == SEEK_STOP)
                return come_to_rest(homing_found_ ? MOTION_RESULT_HOMED : MOTION_RESULT_SWITCH_NOT_FOUND);
            return come_to_rest(MOTION_RESULT_STOPPED);
        }
    }
    advance(velocity, out);
}

// ---- reports -----------------------------------------------------------------------------------------------

int32_t Axis::mdeg_to_steps(int32_t mdeg) const { return (int32_t)lroundf((float)mdeg / mdeg_per_step_); }

int32_t Axis::steps_to_mdeg(int32_t steps) const {
    return configured() ? (int32_t)lroundf((float)steps * mdeg_per_step_) : 0;
}

int32_t Axis::velocity_mdeg_s() const {
    float mdeg_s = (float)velocity_q24_ * (mdeg_per_step_ * WINDOWS_PER_S / (float)Q24_ONE);
    int32_t speed = (int32_t)lroundf(mdeg_s);
    return direction_ > 0 ? speed : -speed;
}

bool Axis::switch_active() const {
    return has(config_.options, MOTION_OPTIONS_HOME_SWITCH) &&
           home_input_high_ != has(config_.options, MOTION_OPTIONS_SWITCH_ACTIVE_LOW);
}

uint8_t Axis::flags() const {
    return (uint8_t)((enabled_ << MOTION_FLAGS_ENABLED) | (referenced_ << MOTION_FLAGS_REFERENCED) |
                     (switch_homed_ << MOTION_FLAGS_SWITCH_HOMED) | (switch_active() << MOTION_FLAGS_SWITCH_ACTIVE));
}

void Axis::set_state(uint8_t state, uint8_t result) {
    if (state != state_ || result != result_) changed_ = true;
    state_ = state;
    result_ = result;
}

// ---- both axes ---------------------------------------------------------------------------------------------

uint8_t Motion::move_to(uint8_t n, int32_t angle_mdeg) {
    if (axes_[n ^ 1].state() >= MOTION_STATE_MOVING) return STATUS_BUSY;
    return axes_[n].move_to(angle_mdeg);
}

uint8_t Motion::home(uint8_t n, uint8_t method, int32_t angle_mdeg) {
    if (method != HOME_METHOD_HERE && axes_[n ^ 1].state() >= MOTION_STATE_MOVING) return STATUS_BUSY;
    return axes_[n].home(method, angle_mdeg);
}

void Motion::stop(bool release) {
    for (uint8_t n = 0; n < AXES; ++n) axes_[n].stop(release);
}

void Motion::halt() {
    for (uint8_t n = 0; n < AXES; ++n) {
        axes_[n].halt();
        plans_[0].axis[n].count = plans_[1].axis[n].count = 0;
    }
}

void Motion::tick(const MotionSample& sample) {
    for (uint8_t n = 0; n < AXES; ++n) axes_[n].sample((sample.home_inputs >> n) & 1, sample.unmade_steps[n]);
    if (!sample.window_start) return;
    if (axes_[0].busy() || axes_[1].busy()) return plan_window();
    if (plans_[current_].axis[0].count | plans_[current_].axis[1].count) {
        // the last steps were handed over in the last window: an empty plan, in the other buffer
        uint8_t dir_high = plans_[current_].dir_high;
        current_ ^= 1;
        plans_[current_] = StepPlan{dir_high, {{0, 0, 0}, {0, 0, 0}}};
    }
}

// Each axis's steps of the next window, into the buffer the AVR layer is not making.
void Motion::plan_window() {
    current_ ^= 1;
    StepPlan& plan = plans_[current_];
    plan.dir_high = 0;
    for (uint8_t n = 0; n < AXES; ++n) {
        axes_[n].plan_window(plan.axis[n]);
        if (axes_[n].dir_high()) plan.dir_high |= (uint8_t)(1u << n);
    }
}

uint8_t Motion::enabled_mask() const {
    uint8_t mask = 0;
    for (uint8_t n = 0; n < AXES; ++n)
        if (axes_[n].enabled()) mask |= (uint8_t)(1u << n);
    return mask;
}

bool Motion::changed() const {
    for (uint8_t n = 0; n < AXES; ++n)
        if (axes_[n].changed()) return true;
    return false;
}

void Motion::clear_changed() {
    for (uint8_t n = 0; n < AXES; ++n) axes_[n].clear_changed();
}


}  // namespace core
