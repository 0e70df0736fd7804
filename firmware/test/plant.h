// A simple pneumatic plant for the native tests: one chamber per physics.md (isothermal gas in a compliant
// chamber, a blower whose flow falls with back-pressure, a leak back through the idle blower), and the
// MPXV7025G sensor read by a 10-bit ratiometric ADC. Integrated with explicit Euler at a fine fixed step.
#pragma once
#include <math.h>
#include <stdint.h>

namespace plant {

struct Chamber {
    double pressure_pa = 0;
    double atmosphere_pa = 101300;
    double free_flow_m3_s = 8.3e-6;      // about 0.5 L/min at no back-pressure
    double blocked_pressure_pa = 10000;  // flow falls to zero at 10 kPa
    double leak_m3_s_per_pa = 8.3e-10;   // 0.1 L/min out at 2 kPa
    double air_volume_m3 = 7e-6;         // chamber plus tubing at rest
    double compliance_m3_per_pa = 2.5e-9;  // 2.5 ml/kPa

    // Advance by dt_s with drive level u in [0, 1]: dp/dt = p_atm (Q_in - Q_out) / (V + (p_atm + p) C).
    void advance(double u, double dt_s) {
        double inflow = free_flow_m3_s * u * (1.0 - pressure_pa / blocked_pressure_pa);
        if (inflow < 0) inflow = 0;
        double outflow = leak_m3_s_per_pa * pressure_pa;
        double volume = air_volume_m3 + compliance_m3_per_pa * pressure_pa;
        pressure_pa += dt_s * atmosphere_pa * (inflow - outflow) / (volume + (atmosphere_pa + pressure_pa) * compliance_m3_per_pa);
    }
};

// The ADC reading (0..1023) of the sensor at a gauge pressure: Vout / Vs = 0.018 P[kPa] + 0.5, 1024 counts = Vs.
inline uint16_t adc_counts(double pressure_pa) {
    double counts = floor(1024.0 * (0.018 * pressure_pa / 1000.0 + 0.5));
    if (counts < 0) return 0;
    if (counts > 1023) return 1023;
    return (uint16_t)counts;
}

}  // namespace plant
