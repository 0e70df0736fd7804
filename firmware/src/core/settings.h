// The settings kept in EEPROM across resets: each sensor's zero, each chamber's PID gains and pressure limit.
// One block: layout version, the fields, CRC-16 (the frame's CRC) over version and fields. An erased EEPROM
// (version byte 0xFF) holds no block; another version, a bad CRC or a value out of range is a corrupt block.
// Either way the controller starts from compiled defaults, and BOARD_INFO says which.
#pragma once
#include <stdint.h>

#include "config.h"
#include "pid.h"

namespace core {

struct Settings {
    int16_t zero_x16[CHAMBERS];  // 0 = never measured
    PidGains gains[CHAMBERS];
    int16_t max_pressure_pa[CHAMBERS];
};

const uint8_t SETTINGS_LAYOUT_VERSION = 1;
// version + zeros + (3 floats + u16) per chamber + limits + CRC
const uint8_t SETTINGS_BYTES = 1 + 2 * CHAMBERS + 14 * CHAMBERS + 2 * CHAMBERS + 2;

// The block for these settings.
void settings_encode(const Settings& settings, uint8_t out[SETTINGS_BYTES]);

// Read a block: CONFIG_SOURCE_EEPROM with `settings` filled, else CONFIG_SOURCE_DEFAULTS (no block) or
// CONFIG_SOURCE_CORRUPT, with `settings` untouched.
uint8_t settings_decode(const uint8_t in[SETTINGS_BYTES], Settings& settings);

}  // namespace core
