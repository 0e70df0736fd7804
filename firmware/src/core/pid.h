// One chamber's pressure PID in fixed point: fixed sample time, derivative on measurement, one-sided output
// with anti-windup, bumpless gain changes. Drive levels are Q28 inside (1.0 = 2^28) and u16 outside
// (65535 = 1.0); pressures are Pa.
#pragma once
#include <stdint.h>

namespace core {

// Gains as the wire carries them, and the ranges set() accepts.
struct PidGains {
    float kp_per_kpa;     // drive level per kPa of error, 0..MAX_KP_PER_KPA
    float ki_per_kpa_s;   // drive level per kPa*s of accumulated error, 0..MAX_KI_PER_KPA_S
    float kd_s_per_kpa;   // drive level per kPa/s of pressure rise (on the measurement only), 0..MAX_KD_S_PER_KPA
    uint16_t max_drive;   // output ceiling, 65535 = 1.0
};
const float MAX_KP_PER_KPA = 100.0f;
const float MAX_KI_PER_KPA_S = 1000.0f;
const float MAX_KD_S_PER_KPA = 1.0f;

// Whether gains are finite and inside the accepted ranges.
bool pid_gains_valid(const PidGains& gains);

class Pid {
public:
    // Set the gains (valid ones) and start from rest; the sample time is 1 / TICK_HZ.
    void init(const PidGains& gains);

    // Change gains without a jump in the output: the integrator absorbs the proportional term's change.
    void set_gains(const PidGains& gains);

    // Forget the past (integrator, derivative state, output); the next step starts from rest at pressure_pa.
    void reset(int16_t pressure_pa);

    // One control step: the drive level (65535 = 1.0, at most max_drive) for a setpoint and a measured pressure.
    uint16_t step(int16_t setpoint_pa, int16_t pressure_pa);

    const PidGains& gains() const { return gains_; }
    // Integrator state as a drive level (65535 = 1.0).
    uint16_t integral() const { return (uint16_t)(integral_q28_ >> 12); }

private:
    // A gain in Q28 per Pa (or per Pa per tick) and the largest |input| whose product stays inside +-2^29.
    struct Scaled {
        int32_t gain_q28;
        int32_t input_limit;
    };
    static const int32_t NO_LIMIT = 0x7FFFFFFF;
    static Scaled scale(float gain_per_pa);
    static int32_t product(const Scaled& gain, int32_t input);

    PidGains gains_;
    Scaled kp_ = {0, NO_LIMIT};  // per Pa
    Scaled ki_ = {0, NO_LIMIT};  // per Pa per tick
    Scaled kd_ = {0, NO_LIMIT};  // per Pa of change per tick
    int32_t max_drive_q28_ = 0;
    int32_t integral_q28_ = 0;
    int32_t derivative_q28_ = 0;
    int16_t last_pressure_pa_ = 0;
    int32_t last_error_pa_ = 0;
};

}  // namespace core
