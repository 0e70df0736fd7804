#include "settings.h"

#include "crc16.h"
#include "protocol_generated.h"
#include "sensor.h"

namespace core {

using namespace proto;

void settings_encode(const Settings& settings, uint8_t out[SETTINGS_BYTES]) {
    uint8_t* p = out;
    *p++ = SETTINGS_LAYOUT_VERSION;
    for (uint8_t i = 0; i < CHAMBERS; ++i, p += 2) put_u16(p, (uint16_t)settings.zero_x16[i]);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        put_f32(p, settings.gains[i].kp_per_kpa);
        put_f32(p + 4, settings.gains[i].ki_per_kpa_s);
        put_f32(p + 8, settings.gains[i].kd_s_per_kpa);
        put_u16(p + 12, settings.gains[i].max_drive);
        p += 14;
    }
    for (uint8_t i = 0; i < CHAMBERS; ++i, p += 2) put_u16(p, (uint16_t)settings.max_pressure_pa[i]);
    put_u16(p, crc16(out, (uint8_t)(p - out)));
}

// Every value must be one the controller itself would have accepted: a block that passes its CRC but holds
// something else was written by other firmware.
static bool plausible(const Settings& s) {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        int16_t offset = (int16_t)(s.zero_x16[i] - NOMINAL_ZERO_X16);
        if (s.zero_x16[i] != 0 && (offset > ZERO_MAX_OFFSET_X16 || offset < -ZERO_MAX_OFFSET_X16)) return false;
        if (!pid_gains_valid(s.gains[i])) return false;
        if (s.max_pressure_pa[i] <= 0 || s.max_pressure_pa[i] > PRESSURE_CEILING_PA) return false;
    }
    return true;
}

uint8_t settings_decode(const uint8_t in[SETTINGS_BYTES], Settings& settings) {
    if (in[0] == 0xFF) return CONFIG_SOURCE_DEFAULTS;
    if (in[0] != SETTINGS_LAYOUT_VERSION) return CONFIG_SOURCE_CORRUPT;
    if (crc16(in, SETTINGS_BYTES - 2) != get_u16(in + SETTINGS_BYTES - 2)) return CONFIG_SOURCE_CORRUPT;
    Settings read;
    const uint8_t* p = in + 1;
    for (uint8_t i = 0; i < CHAMBERS; ++i, p += 2) read.zero_x16[i] = (int16_t)get_u16(p);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        read.gains[i].kp_per_kpa = get_f32(p);
        read.gains[i].ki_per_kpa_s = get_f32(p + 4);
        read.gains[i].kd_s_per_kpa = get_f32(p + 8);
        read.gains[i].max_drive = get_u16(p + 12);
        p += 14;
    }
    for (uint8_t i = 0; i < CHAMBERS; ++i, p += 2) read.max_pressure_pa[i] = (int16_t)get_u16(p);
    if (!plausible(read)) return CONFIG_SOURCE_CORRUPT;
    settings = read;
    return CONFIG_SOURCE_EEPROM;
}

}  // namespace core
