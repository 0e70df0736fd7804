#include "frame.h"

#include "cobs.h"
#include "crc16.h"

namespace core {

// Build one wire frame: header, payload, CRC, COBS, delimiter.
uint8_t frame_encode(uint8_t msg_id, uint8_t seq, const uint8_t* payload, uint8_t payload_len, uint8_t* out) {
    uint8_t body[proto::MAX_BODY_BYTES];
    body[0] = msg_id;
    body[1] = seq;
    if (payload_len) memcpy(body + 2, payload, payload_len);
    uint16_t crc = crc16(body, (uint8_t)(payload_len + 2));
    body[payload_len + 2] = (uint8_t)crc;
    body[payload_len + 3] = (uint8_t)(crc >> 8);
    uint8_t len = (uint8_t)cobs_encode(body, (uint8_t)(payload_len + 4), out);
    out[len] = 0;
    return (uint8_t)(len + 1);
}

// Accumulate one byte; decode and check the frame when a delimiter arrives.
bool FrameReader::feed(uint8_t byte) {
    if (byte != 0) {
        if (discarding_) return false;
        if (encoded_len_ == MAX_ENCODED_BYTES) {
            ++overflow;
            encoded_len_ = 0;
            discarding_ = true;
            return false;
        }
        encoded_[encoded_len_++] = byte;
        return false;
    }
    if (discarding_) {
        discarding_ = false;
        return false;
    }
    if (encoded_len_ == 0) return false;
    bool good = finish();
    encoded_len_ = 0;
    return good;
}

// Check a delimited frame in the order CRC, id, length; count why it is dropped.
bool FrameReader::finish() {
    int len = cobs_decode(encoded_, encoded_len_, body_);
    if (len < 0) {
        ++bad_frame;
        return false;
    }
    if (len < 4 || len > proto::MAX_BODY_BYTES) {
        ++(len > proto::MAX_BODY_BYTES ? overflow : bad_frame);
        return false;
    }
    uint16_t crc = (uint16_t)(body_[len - 2] | (body_[len - 1] << 8));
    if (crc16(body_, (uint8_t)(len - 2)) != crc) {
        ++bad_crc;
        return false;
    }
    bool id_ok = accept_board_ids_ ? proto::payload_size(body_[0]) >= 0 : proto::sent_by_host(body_[0]);
    if (!id_ok || proto::payload_size(body_[0]) != len - 4) {
        ++bad_frame;
        return false;
    }
    body_len_ = (uint8_t)len;
    ++frames_ok;
    return true;
}

}  // namespace core
