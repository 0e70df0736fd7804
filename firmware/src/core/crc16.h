// CRC-16/MCRF4XX, the frame check of the wire protocol.
#pragma once
#include <stdint.h>

namespace core {

// Fold one byte into a CRC-16/MCRF4XX (poly 0x8408 reflected, init 0xFFFF, no final xor).
uint16_t crc16_update(uint16_t crc, uint8_t byte);

// CRC-16/MCRF4XX of a buffer, starting from 0xFFFF.
uint16_t crc16(const uint8_t* data, uint8_t len);

}  // namespace core
