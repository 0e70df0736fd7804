// The reciprocal of a 9-bit mantissa from a table in flash: how the stepper planning divides by a velocity
// once per tick in a few tens of cycles (a 32-bit division takes about 640 on the AVR).
#pragma once
#include <stdint.h>

namespace core {

// 2^24 / mantissa, rounded down (65535 for 256), for mantissa = 256..511.
uint16_t reciprocal_q24(uint16_t mantissa);

}  // namespace core
