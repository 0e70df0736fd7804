// Compile-time constants of the firmware. The limits and thresholds the host must also know come from
// protocol/spec.toml ([constants], generated into proto::); only what is the firmware's own business is here.
#pragma once
#include <stdint.h>

#include "protocol_generated.h"

namespace core {

const uint8_t FIRMWARE_MAJOR = 0;
const uint8_t FIRMWARE_MINOR = 4;
const uint8_t FIRMWARE_PATCH = 0;

const uint8_t CHAMBERS = 3;
static_assert(CHAMBERS == proto::CHAMBER_COUNT, "the firmware's chamber count must match protocol/spec.toml");

using proto::TICK_HZ;
const uint8_t TICK_MS = 1000 / TICK_HZ;  // board time advances by this much per tick
static_assert(1000 % TICK_HZ == 0, "a tick must be a whole number of milliseconds");

// Over-pressure: the host sets a per-chamber limit, clamped to the ceiling, which is also checked on its own
// against the lower of the measured zeros and the nominal zero (Controller::check_safety).
using proto::DEFAULT_MAX_PRESSURE_PA;
using proto::PRESSURE_CEILING_PA;

// Default PID gains for the plant of the project's physics notes (see firmware/README.md).
const float DEFAULT_KP_PER_KPA = 4.0f;
const float DEFAULT_KI_PER_KPA_S = 15.0f;
const float DEFAULT_KD_S_PER_KPA = 0.0f;

// Sensor fault: a reading outside the band (sensor.h) or a tick without a conversion, SENSOR_BAD_TICKS in a row.
using proto::SENSOR_BAD_TICKS;
// Leak: the blower at its ceiling while the reading stays more than LEAK_MIN_ERROR_PA below the setpoint for
// LEAK_TIME_MS. The default plant's blower runs at full drive for about 0.4 s of a 0 -> 2 kPa step and 0.8 s of
// a 0 -> 3 kPa one; 2 s leaves room for a slower blower, and 200 Pa (about 4 ADC counts) is far above the noise.
using proto::LEAK_MIN_ERROR_PA;
const uint16_t LEAK_TICKS = proto::LEAK_TIME_MS / TICK_MS;
// Plausibility: a reading that does not move under a high drive is a sensor that does not see its chamber
// (tube off, stuck). Any chamber's reading moves by tens of Pa per tick at full drive.
using proto::PLAUSIBLE_MIN_CHANGE_PA;
using proto::PLAUSIBLE_MIN_DRIVE;
const uint16_t PLAUSIBLE_TICKS = proto::PLAUSIBLE_TIME_MS / TICK_MS;
// Zero: measured over ZERO_TICKS once every blower has been off and every reading within ZERO_STABLE_PA of
// where it was for ZERO_SETTLE_MS; refused beyond the datasheet's offset tolerance of the nominal zero.
using proto::ZERO_TICKS;
const uint16_t ZERO_SETTLE_TICKS = proto::ZERO_SETTLE_MS / TICK_MS;
// Supply: AVcc measured against the internal 1.1 V reference (its tolerance is +-9 %, see docs/hardware.md).
using proto::SUPPLY_BAD_TICKS;
using proto::SUPPLY_MIN_MV;

// Link defaults and the ranges SET_CONFIG accepts.
using proto::DEFAULT_HOST_DEADLINE_MS;
using proto::DEFAULT_TELEMETRY_PERIOD_MS;
using proto::MAX_HOST_DEADLINE_MS;
using proto::MAX_TELEMETRY_PERIOD_MS;
using proto::MIN_HOST_DEADLINE_MS;
using proto::MIN_TELEMETRY_PERIOD_MS;

// TEST_HANG's magic number, so that a corrupted or stray frame cannot hang the board. Only a bench build
// (PHANTOM_BENCH, `make bench`) obeys TEST_HANG; a production build NACKs it with BAD_MAGIC.
using proto::TEST_HANG_MAGIC;

}  // namespace core
