// COBS byte stuffing: the encoded form holds no 0x00, so 0x00 can delimit frames.
#pragma once
#include <stdint.h>

namespace core {

// Encode len bytes of in into out (room for len + len / 254 + 1 bytes); returns the encoded length.
uint16_t cobs_encode(const uint8_t* in, uint16_t len, uint8_t* out);

// Decode len bytes (no delimiter) into out (room for len bytes); returns the decoded length, or -1 if the
// input holds a 0x00 or a code that runs past its end.
int cobs_decode(const uint8_t* in, uint16_t len, uint8_t* out);

}  // namespace core
