#include "crc16.h"

#ifdef __AVR__
#include <util/crc16.h>
#endif

namespace core {

// avr-libc's _crc_ccitt_update on the AVR (inline assembly, about a third of the C's cycles: every frame's CRC
// is on the CPU budget); the same arithmetic written portably elsewhere, so the native tests run it too.
uint16_t crc16_update(uint16_t crc, uint8_t byte) {
#ifdef __AVR__
    return _crc_ccitt_update(crc, byte);
#else
    byte ^= (uint8_t)crc;
    byte ^= (uint8_t)(byte << 4);
    return (uint16_t)((((uint16_t)byte << 8) | (crc >> 8)) ^ (uint8_t)(byte >> 4) ^ ((uint16_t)byte << 3));
#endif
}

// CRC-16/MCRF4XX of a buffer.
uint16_t crc16(const uint8_t* data, uint8_t len) {
    uint16_t crc = 0xFFFF;
    for (uint8_t i = 0; i < len; ++i) crc = crc16_update(crc, data[i]);
    return crc;
}

}  // namespace core
