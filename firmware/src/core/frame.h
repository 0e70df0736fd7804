// Wire frames: COBS(msg_id | seq | payload | crc16 LE) 0x00, body at most MAX_BODY_BYTES.
#pragma once
#include <stdint.h>

#include "protocol_generated.h"

namespace core {

// Longest encoded frame without its delimiter (one COBS code byte per 254 body bytes, plus one).
const uint8_t MAX_ENCODED_BYTES = proto::MAX_BODY_BYTES + 1;
// Longest frame on the wire, delimiter included.
const uint8_t MAX_FRAME_BYTES = MAX_ENCODED_BYTES + 1;

// Build a whole wire frame into out (MAX_FRAME_BYTES of room); returns its length, delimiter included.
uint8_t frame_encode(uint8_t msg_id, uint8_t seq, const uint8_t* payload, uint8_t payload_len, uint8_t* out);

// Splits a byte stream at 0x00, checks each frame and keeps the last good one; counts the bad ones.
class FrameReader {
public:
    // accept_board_ids: also accept messages the board sends (for tests that read the board's own frames).
    explicit FrameReader(bool accept_board_ids = false) : accept_board_ids_(accept_board_ids) {}

    // Take one byte; true when it completed a good frame (then msg_id(), seq(), payload() describe it).
    bool feed(uint8_t byte);

    uint8_t msg_id() const { return body_[0]; }
    uint8_t seq() const { return body_[1]; }
    const uint8_t* payload() const { return body_ + 2; }
    uint8_t payload_len() const { return (uint8_t)(body_len_ - 4); }

    uint16_t frames_ok = 0;
    uint16_t bad_crc = 0;     // CRC mismatch
    uint16_t overflow = 0;    // more than MAX_ENCODED_BYTES before a delimiter
    uint16_t bad_frame = 0;   // bad COBS, body too short, unknown or board-only id, or wrong payload length

private:
    bool finish();

    uint8_t encoded_[MAX_ENCODED_BYTES];
    uint8_t body_[MAX_ENCODED_BYTES];
    uint8_t encoded_len_ = 0;
    uint8_t body_len_ = 0;
    bool discarding_ = false;
    bool accept_board_ids_;
};

}  // namespace core
