// The golden vectors of protocol/vectors, decoded and re-encoded by the firmware's codec.
#include <string.h>

#include "check.h"
#include "core/frame.h"
#include "core/protocol_generated.h"

struct Decoded {
    bool ok;
    uint8_t msg_id, seq, payload_len;
    uint8_t payload[proto::MAX_BODY_BYTES];
};

// Run a whole wire frame through a reader that accepts every message id; exactly one frame must come out.
static Decoded decode_frame(const uint8_t* frame, size_t len) {
    Decoded d;
    memset(&d, 0, sizeof d);
    core::FrameReader reader(true);
    int frames = 0;
    for (size_t i = 0; i < len; ++i) {
        if (!reader.feed(frame[i])) continue;
        ++frames;
        d.msg_id = reader.msg_id();
        d.seq = reader.seq();
        d.payload_len = reader.payload_len();
        memcpy(d.payload, reader.payload(), d.payload_len);
    }
    d.ok = frames == 1;
    return d;
}

// Encode a payload into a frame and compare it byte for byte with the golden frame.
static void check_reencoded(uint8_t msg_id, uint8_t seq, const uint8_t* payload, uint8_t payload_len,
                            const uint8_t* frame, size_t frame_len) {
    uint8_t out[core::MAX_FRAME_BYTES];
    uint8_t len = core::frame_encode(msg_id, seq, payload, payload_len, out);
    CHECK_EQ(len, frame_len);
    CHECK(len == frame_len && memcmp(out, frame, len) == 0);
}

#include "golden_vectors.inc"

int main() { return check::run_all("golden vectors (C++ codec)"); }
