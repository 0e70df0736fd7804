#include "sensor.h"

namespace core {

// sum * 16 / count, rounded; the usual count of 4 is a shift.
int16_t sensor_average_x16(uint16_t sum, uint8_t count) {
    if (count == 4) return (int16_t)(sum << 2);
    if (count == 0) return 0;
    return (int16_t)(((uint32_t)sum * COUNTS_X16 + count / 2) / count);
}

// P = (reading - zero) * 13889 / 4096, rounded to the nearest Pa (halves upward); a shift, not a division,
// because this runs three times per tick. |reading - zero| < 2^14 keeps the product inside an int32.
int16_t sensor_x16_to_pa(int16_t counts_x16, int16_t zero_x16) {
    int32_t scaled = (int32_t)(counts_x16 - zero_x16) * PA_PER_COUNT_X16_Q12;
    return (int16_t)((scaled + 2048) >> 12);
}

// reading = zero + P * 4096 / 13889, rounded to the nearest sixteenth of a count.
int16_t sensor_pa_to_x16(int16_t pressure_pa, int16_t zero_x16) {
    int32_t scaled = (int32_t)pressure_pa * 4096;
    int32_t half = PA_PER_COUNT_X16_Q12 / 2;
    return (int16_t)(zero_x16 + (scaled + (scaled >= 0 ? half : -half)) / PA_PER_COUNT_X16_Q12);
}

// Valid band check.
bool sensor_in_range(int16_t counts_x16) {
    return counts_x16 >= SENSOR_MIN_VALID_X16 && counts_x16 <= SENSOR_MAX_VALID_X16;
}

}  // namespace core
