// Compile-time constants of the firmware: rates, limits the host cannot raise, and defaults it can change.
#pragma once
#include <stdint.h>

namespace core {

const uint8_t FIRMWARE_MAJOR = 0;
const uint8_t FIRMWARE_MINOR = 2;
const uint8_t FIRMWARE_PATCH = 0;

const uint16_t TICK_HZ = 500;                 // control rate
const uint8_t TICK_MS = 1000 / TICK_HZ;       // board time advances by this much per tick
const uint8_t CHAMBERS = 3;

// Over-pressure: the host sets a per-chamber limit, clamped to this ceiling (the phantom uses 0-3 kPa).
const int16_t PRESSURE_CEILING_PA = 6000;
const int16_t DEFAULT_MAX_PRESSURE_PA = 4000;

// Default PID gains for the plant of physics.md (see firmware/README.md for how they were chosen).
const float DEFAULT_KP_PER_KPA = 4.0f;
const float DEFAULT_KI_PER_KPA_S = 15.0f;
const float DEFAULT_KD_S_PER_KPA = 0.0f;

// Sensor fault: consecutive out-of-band ticks that latch it (sensor.h has the band).
const uint8_t SENSOR_BAD_TICKS = 5;                // consecutive out-of-range ticks that latch the fault
// Leak (a chamber that cannot reach or hold its setpoint): the blower at its ceiling while the reading stays
// more than LEAK_MIN_ERROR_PA below the setpoint, LEAK_TICKS in a row. The default plant's blower runs at full
// drive for about 0.4 s of a 0 -> 2 kPa step and 0.8 s of a 0 -> 3 kPa one; 2 s leaves room for a slower
// blower, and 200 Pa (about 4 ADC counts) is far above the sensor noise.
const int16_t LEAK_MIN_ERROR_PA = 200;
const uint16_t LEAK_TICKS = 2 * TICK_HZ;           // 2 s
// A measured zero further than this from the nominal zero is refused (the datasheet's 5 % of the 50 kPa span
// is 46 counts), in sixteenths of a count.
const int16_t ZERO_MAX_OFFSET_X16 = 46 * 16;
const uint8_t ZERO_TICKS = 64;                     // ticks averaged by ZERO_SENSORS (128 ms)

// Link defaults and the ranges SET_CONFIG accepts.
const uint16_t DEFAULT_TELEMETRY_PERIOD_MS = 20;
const uint16_t MIN_TELEMETRY_PERIOD_MS = 10;
const uint16_t MAX_TELEMETRY_PERIOD_MS = 1000;
const uint16_t DEFAULT_HOST_DEADLINE_MS = 500;
const uint16_t MIN_HOST_DEADLINE_MS = 50;
const uint16_t MAX_HOST_DEADLINE_MS = 10000;

// TEST_HANG's magic number, so that a corrupted or stray frame cannot hang the board.
const uint32_t TEST_HANG_MAGIC = 0x48414E47UL;

}  // namespace core
