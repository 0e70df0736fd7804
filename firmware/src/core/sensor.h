// Pressure sensor conversion in integers: averaged ADC counts (in sixteenths of a count) to gauge pressure
// in Pa, with a zero offset. MPXV7025G: Vout / Vs = 0.018 P[kPa] + 0.5, read ratiometrically (1024 counts = Vs).
#pragma once
#include <stdint.h>

#include "protocol_generated.h"

namespace core {

// Sixteenths of an ADC count per count: readings are averaged and kept with 4 fractional bits.
const int16_t COUNTS_X16 = 16;
// Nominal reading at 0 kPa: Vs / 2 = 512 counts.
const int16_t NOMINAL_ZERO_X16 = proto::ADC_FULL_SCALE_COUNTS / 2 * COUNTS_X16;
// Valid band 0.1 V .. 4.9 V of 5 V, 1/50 and 49/50 of the full scale, rounded: 20.48 .. 1003.52 counts, 328 ..
// 16056 sixteenths (a reading outside means a broken wire or sensor).
const int16_t SENSOR_MIN_VALID_X16 = (int16_t)(((int32_t)proto::ADC_FULL_SCALE_COUNTS * COUNTS_X16 + 25) / 50);
const int16_t SENSOR_MAX_VALID_X16 = (int16_t)(((int32_t)proto::ADC_FULL_SCALE_COUNTS * COUNTS_X16 * 49 + 25) / 50);
// Pa per sixteenth of a count, as a fraction over 2^12, rounded: 1000 / (0.018 * 1024 * 16) = 3.390842 =
// 13888.9 / 4096, from the spec's sensitivity and full scale (1000 Pa per kPa times 1000 per mille).
const int64_t PA_PER_COUNT_X16_DIVISOR =
    (int64_t)proto::SENSOR_PERMILLE_PER_KPA * proto::ADC_FULL_SCALE_COUNTS * COUNTS_X16;
const int32_t PA_PER_COUNT_X16_Q12 =
    (int32_t)((1000000LL * 4096 + PA_PER_COUNT_X16_DIVISOR / 2) / PA_PER_COUNT_X16_DIVISOR);

// The spec's zero thresholds in sixteenths of a count (1 x16 = 3.39 Pa).
const int16_t ZERO_MAX_OFFSET_X16 = (int16_t)((int32_t)proto::ZERO_MAX_OFFSET_PA * 4096 / PA_PER_COUNT_X16_Q12);
const int16_t ZERO_STABLE_X16 = (int16_t)((int32_t)proto::ZERO_STABLE_PA * 4096 / PA_PER_COUNT_X16_Q12);

// Average of `count` 10-bit conversions whose sum is `sum`, in sixteenths of a count (0 if count is 0).
int16_t sensor_average_x16(uint16_t sum, uint8_t count);

// Gauge pressure in Pa of an averaged reading, given the reading at 0 Pa (both in sixteenths of a count).
int16_t sensor_x16_to_pa(int16_t counts_x16, int16_t zero_x16);

// The averaged reading (sixteenths of a count, rounded) that a gauge pressure in Pa gives.
int16_t sensor_pa_to_x16(int16_t pressure_pa, int16_t zero_x16);

// Whether an averaged reading lies inside the sensor's valid output band.
bool sensor_in_range(int16_t counts_x16);

}  // namespace core
