#include "cobs.h"

namespace core {

// COBS-encode a buffer.
uint16_t cobs_encode(const uint8_t* in, uint16_t len, uint8_t* out) {
    uint16_t code_at = 0;
    uint16_t out_len = 1;
    uint8_t code = 1;
    for (uint16_t i = 0; i < len; ++i) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = out_len++;
            code = 1;
            continue;
        }
        out[out_len++] = in[i];
        if (++code == 0xFF) {
            out[code_at] = code;
            code_at = out_len++;
            code = 1;
        }
    }
    out[code_at] = code;
    return out_len;
}

// Undo cobs_encode; -1 on malformed input.
int cobs_decode(const uint8_t* in, uint16_t len, uint8_t* out) {
    uint16_t index = 0;
    uint16_t out_len = 0;
    while (index < len) {
        uint8_t code = in[index];
        if (code == 0 || index + code > len) return -1;
        for (uint8_t i = 1; i < code; ++i) {
            uint8_t byte = in[index + i];
            if (byte == 0) return -1;
            out[out_len++] = byte;
        }
        index = (uint16_t)(index + code);
        if (code != 0xFF && index < len) out[out_len++] = 0;
    }
    return out_len;
}

}  // namespace core
