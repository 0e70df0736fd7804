#include "pid.h"

#include "config.h"

namespace core {

// Q28: one drive level unit; products and the derivative are kept inside +-2 units, so that the sum of the
// three terms and the integrator (at most 1 unit) never overflows an int32.
static const int32_t ONE_Q28 = (int32_t)1 << 28;
static const int32_t TERM_LIMIT_Q28 = (int32_t)1 << 29;

// value limited to [low, high].
static int32_t clamp(int32_t value, int32_t low, int32_t high) {
    return value < low ? low : (value > high ? high : value);
}

// Finite, non-negative and not above the documented maxima (a NaN fails every comparison).
bool pid_gains_valid(const PidGains& gains) {
    return gains.kp_per_kpa >= 0.0f && gains.kp_per_kpa <= MAX_KP_PER_KPA && gains.ki_per_kpa_s >= 0.0f &&
           gains.ki_per_kpa_s <= MAX_KI_PER_KPA_S && gains.kd_s_per_kpa >= 0.0f &&
           gains.kd_s_per_kpa <= MAX_KD_S_PER_KPA;
}

// gain * 2^28, rounded, with the input magnitude beyond which the product saturates at +-2^29.
Pid::Scaled Pid::scale(float gain_per_pa) {
    Scaled scaled;
    scaled.gain_q28 = (int32_t)(gain_per_pa * (float)ONE_Q28 + 0.5f);
    scaled.input_limit = scaled.gain_q28 > 0 ? TERM_LIMIT_Q28 / scaled.gain_q28 : NO_LIMIT;
    return scaled;
}

// gain * input, saturated to +-2^29 without a runtime division.
int32_t Pid::product(const Scaled& gain, int32_t input) {
    if (input > gain.input_limit) return TERM_LIMIT_Q28;
    if (input < -gain.input_limit) return -TERM_LIMIT_Q28;
    return gain.gain_q28 * input;
}

// Store the gains and start from rest.
void Pid::init(const PidGains& gains) {
    set_gains(gains);
    reset(0);
}

// Bumpless: keep P + I unchanged at the last error by re-seeding the integrator.
void Pid::set_gains(const PidGains& gains) {
    int32_t old_proportional = product(kp_, last_error_pa_);
    const float sample_time_s = 1.0f / TICK_HZ;
    gains_ = gains;
    kp_ = scale(gains.kp_per_kpa * 1e-3f);
    ki_ = scale(gains.ki_per_kpa_s * 1e-3f * sample_time_s);
    kd_ = scale(gains.kd_s_per_kpa * 1e-3f / sample_time_s);
    max_drive_q28_ = (int32_t)gains.max_drive << 12;
    if (!kd_.gain_q28) derivative_q28_ = 0;  // no derivative gain, no derivative term (else it would freeze)
    int32_t new_proportional = product(kp_, last_error_pa_);
    integral_q28_ = clamp(integral_q28_ + old_proportional - new_proportional, 0, max_drive_q28_);
}

// Back to rest: no stored integral or derivative, last measurement pressure_pa.
void Pid::reset(int16_t pressure_pa) {
    integral_q28_ = 0;
    derivative_q28_ = 0;
    last_pressure_pa_ = pressure_pa;
    last_error_pa_ = 0;
}

// u = kp e + I - kd dp/dt (low-passed), clamped to [0, max_drive]; I integrates ki e only while that does not
// push u further into saturation (conditional integration) and stays inside [0, max_drive] itself.
uint16_t Pid::step(int16_t setpoint_pa, int16_t pressure_pa) {
    int32_t error_pa = (int32_t)setpoint_pa - pressure_pa;
    if (kd_.gain_q28) {
        int32_t raw_derivative = -product(kd_, (int32_t)pressure_pa - last_pressure_pa_);
        derivative_q28_ += (raw_derivative - derivative_q28_) >> 2;  // low-pass, time constant about 4 ticks
    }
    last_pressure_pa_ = pressure_pa;
    last_error_pa_ = error_pa;

    int32_t proportional = product(kp_, error_pa);
    int32_t candidate = integral_q28_ + product(ki_, error_pa);
    int32_t unclamped = proportional + candidate + derivative_q28_;
    bool winding_up = (unclamped > max_drive_q28_ && error_pa > 0) || (unclamped < 0 && error_pa < 0);
    if (!winding_up) integral_q28_ = clamp(candidate, 0, max_drive_q28_);
    int32_t output = clamp(proportional + integral_q28_ + derivative_q28_, 0, max_drive_q28_);
    return (uint16_t)(output >> 12);
}

}  // namespace core
