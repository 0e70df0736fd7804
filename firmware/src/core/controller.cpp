#include "controller.h"

#include "sensor.h"

namespace core {

using namespace proto;

// Safe start: every chamber off with default gains and the nominal sensor zero.
void Controller::init(uint8_t board, uint8_t reset_cause, SendFrame send, void* context) {
    board_ = board;
    reset_cause_ = reset_cause;
    send_frame_ = send;
    send_context_ = context;
    PidGains gains = {DEFAULT_KP_PER_KPA, DEFAULT_KI_PER_KPA_S, DEFAULT_KD_S_PER_KPA, 65535};
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        pid_[i].init(gains);
        zero_x16_[i] = NOMINAL_ZERO_X16;
        counts_x16_[i] = NOMINAL_ZERO_X16;
    }
    if (reset_cause == RESET_CAUSE_WATCHDOG) latch_fault(FAULT_WATCHDOG_RESET);
}

// What a chamber is doing now, for telemetry.
uint8_t Controller::chamber_state(uint8_t chamber) const {
    if (fault_flags_) return CHAMBER_STATE_FAULT;
    if (zero_ticks_left_) return CHAMBER_STATE_ZEROING;
    return setpoint_pa_[chamber] > 0 ? CHAMBER_STATE_REGULATING : CHAMBER_STATE_OFF;
}

// Feed the frame reader; any valid frame counts as a sign of life from the host.
void Controller::receive(uint8_t byte) {
    if (!reader_.feed(byte)) return;
    last_rx_ms_ = time_ms_;
    handle_frame();
}

// Dispatch one valid frame; acknowledged commands other than VENT need an open session.
void Controller::handle_frame() {
    uint8_t id = reader_.msg_id();
    uint8_t seq = reader_.seq();
    const uint8_t* payload = reader_.payload();
    if (id == MSG_HELLO) return on_hello(payload);
    if (id == MSG_PING) {
        Pong pong;
        pong.host_time_ms = get_u32(payload);
        pong.board_time_ms = time_ms_;
        uint8_t out[Pong::PAYLOAD_SIZE];
        encode(pong, out);
        return send(MSG_PONG, out, sizeof out);
    }
    if (id == MSG_VENT) return on_vent(seq);
    if (!session_open_) return reply(id, seq, STATUS_NO_SESSION);
    switch (id) {
    case MSG_SET_SETPOINTS: return on_set_setpoints(seq, payload);
    case MSG_SET_PID: return on_set_pid(seq, payload);
    case MSG_SET_CONFIG: return on_set_config(seq, payload);
    case MSG_CLEAR_FAULT: return on_clear_fault(seq);
    case MSG_ZERO_SENSORS: return on_zero_sensors(seq);
    case MSG_TEST_HANG: return on_test_hang(seq, payload);
    default: return;
    }
}

// Answer HELLO with who we are; open the session only if both sides were built from the same spec. A refused
// HELLO also vents: without a session nothing supervises the blowers (no host deadline).
void Controller::on_hello(const uint8_t* payload) {
    Hello hello;
    decode(hello, payload);
    bool match = hello.spec_hash == SPEC_HASH && hello.protocol_version == PROTOCOL_VERSION;
    session_open_ = match;
    if (!match) vent();
    last_telemetry_ms_ = time_ms_;
    HelloReply reply_msg;
    reply_msg.protocol_version = PROTOCOL_VERSION;
    reply_msg.spec_hash = SPEC_HASH;
    reply_msg.status = match ? STATUS_OK : STATUS_SPEC_MISMATCH;
    reply_msg.firmware_major = FIRMWARE_MAJOR;
    reply_msg.firmware_minor = FIRMWARE_MINOR;
    reply_msg.firmware_patch = FIRMWARE_PATCH;
    reply_msg.board = board_;
    reply_msg.chamber_count = CHAMBERS;
    reply_msg.reset_cause = reset_cause_;
    reply_msg.fault_flags = fault_flags_;
    reply_msg.time_ms = time_ms_;
    uint8_t out[HelloReply::PAYLOAD_SIZE];
    encode(reply_msg, out);
    send(MSG_HELLO_REPLY, out, sizeof out);
}

// Absolute setpoints for all chambers, all or nothing; a chamber switched on starts its PID from rest.
void Controller::on_set_setpoints(uint8_t seq, const uint8_t* payload) {
    if (fault_flags_) return reply(MSG_SET_SETPOINTS, seq, STATUS_FAULT_LATCHED);
    if (zero_ticks_left_) return reply(MSG_SET_SETPOINTS, seq, STATUS_BUSY);
    SetSetpoints msg;
    decode(msg, payload);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (msg.setpoint_pa[i] < 0 || msg.setpoint_pa[i] > max_pressure_pa_[i])
            return reply(MSG_SET_SETPOINTS, seq, STATUS_BAD_VALUE);
    }
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (setpoint_pa_[i] == 0 && msg.setpoint_pa[i] > 0) pid_[i].reset(pressure_pa_[i]);
        setpoint_pa_[i] = msg.setpoint_pa[i];
    }
    reply(MSG_SET_SETPOINTS, seq, STATUS_OK);
}

// Gains and limits of one chamber; the limit is clamped to the compile-time ceiling (ACK CLAMPED).
void Controller::on_set_pid(uint8_t seq, const uint8_t* payload) {
    SetPid msg;
    decode(msg, payload);
    if (msg.chamber >= CHAMBERS) return reply(MSG_SET_PID, seq, STATUS_BAD_CHAMBER);
    PidGains gains = {msg.kp_per_kpa, msg.ki_per_kpa_s, msg.kd_s_per_kpa, msg.max_drive};
    if (!pid_gains_valid(gains) || msg.max_pressure_pa <= 0) return reply(MSG_SET_PID, seq, STATUS_BAD_VALUE);
    int16_t limit = msg.max_pressure_pa > PRESSURE_CEILING_PA ? PRESSURE_CEILING_PA : msg.max_pressure_pa;
    if (setpoint_pa_[msg.chamber] > limit) return reply(MSG_SET_PID, seq, STATUS_BAD_VALUE);
    pid_[msg.chamber].set_gains(gains);
    max_pressure_pa_[msg.chamber] = limit;
    reply(MSG_SET_PID, seq, limit == msg.max_pressure_pa ? STATUS_OK : STATUS_CLAMPED);
}

// Telemetry period (0 = off) and dead-host deadline, each within its documented range.
void Controller::on_set_config(uint8_t seq, const uint8_t* payload) {
    SetConfig msg;
    decode(msg, payload);
    bool period_ok = msg.telemetry_period_ms == 0 || (msg.telemetry_period_ms >= MIN_TELEMETRY_PERIOD_MS &&
                                                      msg.telemetry_period_ms <= MAX_TELEMETRY_PERIOD_MS);
    bool deadline_ok = msg.host_deadline_ms >= MIN_HOST_DEADLINE_MS && msg.host_deadline_ms <= MAX_HOST_DEADLINE_MS;
    if (!period_ok || !deadline_ok) return reply(MSG_SET_CONFIG, seq, STATUS_BAD_VALUE);
    telemetry_period_ms_ = msg.telemetry_period_ms;
    host_deadline_ms_ = msg.host_deadline_ms;
    reply(MSG_SET_CONFIG, seq, STATUS_OK);
}

// Clear every latched fault, but only when none of their causes is present now.
void Controller::on_clear_fault(uint8_t seq) {
    if (fault_cause_present()) return reply(MSG_CLEAR_FAULT, seq, STATUS_FAULT_ACTIVE);
    fault_flags_ = 0;
    reply(MSG_CLEAR_FAULT, seq, STATUS_OK);
}

// All blowers off now; always obeyed, with or without a session or a fault.
void Controller::on_vent(uint8_t seq) {
    vent();
    reply(MSG_VENT, seq, STATUS_OK);
}

// Start averaging each sensor's zero; the ACK (or NACK) comes when it is done.
void Controller::on_zero_sensors(uint8_t seq) {
    if (fault_flags_) return reply(MSG_ZERO_SENSORS, seq, STATUS_FAULT_LATCHED);
    if (zero_ticks_left_) return reply(MSG_ZERO_SENSORS, seq, STATUS_BUSY);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (setpoint_pa_[i] != 0 || drive_[i] != 0) return reply(MSG_ZERO_SENSORS, seq, STATUS_NOT_VENTED);
    }
    zero_ticks_left_ = ZERO_TICKS;
    zero_seq_ = seq;
    for (uint8_t i = 0; i < CHAMBERS; ++i) zero_sum_x16_[i] = 0;
}

// Bench-only hang: acknowledged first, then the AVR layer stops kicking the watchdog.
void Controller::on_test_hang(uint8_t seq, const uint8_t* payload) {
    if (get_u32(payload) != TEST_HANG_MAGIC) return reply(MSG_TEST_HANG, seq, STATUS_BAD_MAGIC);
    vent();
    reply(MSG_TEST_HANG, seq, STATUS_OK);
    hang_requested_ = true;
}

// One tick: measure, check every fault, then zero or control, then maybe report.
void Controller::tick(const AdcTick& adc, uint16_t missed_ticks) {
    time_ms_ += (uint32_t)TICK_MS * (1u + missed_ticks);
    tick_overruns_ = (uint16_t)(tick_overruns_ + missed_ticks);
    read_sensors(adc);
    check_safety();
    if (zero_ticks_left_) run_zeroing();
    run_control();
    send_telemetry();
}

// Average this tick's ADC conversions; a chamber without a new conversion keeps its last reading.
void Controller::read_sensors(const AdcTick& adc) {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (adc.count[i] == 0) continue;
        counts_x16_[i] = sensor_average_x16(adc.sum[i], adc.count[i]);
        pressure_pa_[i] = sensor_x16_to_pa(counts_x16_[i], zero_x16_[i]);
    }
}

// Sensor band (several ticks in a row), over-pressure and leak (on a valid reading), the dead-host deadline.
void Controller::check_safety() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (!sensor_in_range(counts_x16_[i])) {
            if (bad_ticks_[i] < SENSOR_BAD_TICKS) ++bad_ticks_[i];
            if (bad_ticks_[i] >= SENSOR_BAD_TICKS) latch_fault((uint8_t)(FAULT_SENSOR_0 + i));
            leak_ticks_[i] = 0;
            continue;
        }
        bad_ticks_[i] = 0;
        if (pressure_pa_[i] > max_pressure_pa_[i]) latch_fault((uint8_t)(FAULT_OVERPRESSURE_0 + i));
        check_leak(i);
    }
    if (session_open_ && time_ms_ - last_rx_ms_ > host_deadline_ms_) latch_fault(FAULT_DEAD_HOST);
}

// Count the ticks a chamber's blower spent at its ceiling (the drive of the last tick, the whole tick long)
// while it still reads more than LEAK_MIN_ERROR_PA below its setpoint; LEAK_TICKS in a row latch LEAK_n.
// A chamber that is off, vented or faulted has setpoint 0 and never counts. (A setpoint is 0..6000 Pa, so
// setpoint - LEAK_MIN_ERROR_PA cannot overflow 16 bits.)
void Controller::check_leak(uint8_t chamber) {
    int16_t setpoint_pa = setpoint_pa_[chamber];
    bool starved = setpoint_pa > 0 && drive_[chamber] >= pid_[chamber].gains().max_drive &&
                   pressure_pa_[chamber] < setpoint_pa - LEAK_MIN_ERROR_PA;
    if (!starved) {
        leak_ticks_[chamber] = 0;
        return;
    }
    if (++leak_ticks_[chamber] < LEAK_TICKS) return;
    leak_ticks_[chamber] = 0;
    latch_fault((uint8_t)(FAULT_LEAK_0 + chamber));
}

// Accumulate the zero readings; at the end store them all, or refuse them all if one is implausible.
void Controller::run_zeroing() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) zero_sum_x16_[i] += counts_x16_[i];
    if (--zero_ticks_left_) return;
    int16_t zero[CHAMBERS];
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        zero[i] = (int16_t)((zero_sum_x16_[i] + ZERO_TICKS / 2) / ZERO_TICKS);
        int16_t offset = (int16_t)(zero[i] - NOMINAL_ZERO_X16);
        if (offset > ZERO_MAX_OFFSET_X16 || offset < -ZERO_MAX_OFFSET_X16)
            return reply(MSG_ZERO_SENSORS, zero_seq_, STATUS_ZERO_OUT_OF_RANGE);
    }
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        zero_x16_[i] = zero[i];
        pressure_pa_[i] = sensor_x16_to_pa(counts_x16_[i], zero_x16_[i]);
    }
    reply(MSG_ZERO_SENSORS, zero_seq_, STATUS_OK);
}

// Run each chamber's PID; a chamber that is off, faulted or has a suspect reading gets no drive.
void Controller::run_control() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        bool active = !fault_flags_ && !zero_ticks_left_ && setpoint_pa_[i] > 0;
        if (!active || bad_ticks_[i]) {
            drive_[i] = 0;
            if (!active) pid_[i].reset(pressure_pa_[i]);
            continue;
        }
        drive_[i] = pid_[i].step(setpoint_pa_[i], pressure_pa_[i]);
    }
}

// Stream one TELEMETRY frame per period while a session is open.
void Controller::send_telemetry() {
    if (!session_open_ || telemetry_period_ms_ == 0) return;
    if (time_ms_ - last_telemetry_ms_ < telemetry_period_ms_) return;
    last_telemetry_ms_ = time_ms_;
    Telemetry msg;
    msg.time_ms = time_ms_;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        msg.pressure_pa[i] = pressure_pa_[i];
        msg.setpoint_pa[i] = setpoint_pa_[i];
        msg.drive[i] = drive_[i];
        msg.state[i] = chamber_state(i);
    }
    msg.fault_flags = fault_flags_;
    msg.rx_bad_crc = reader_.bad_crc;
    msg.rx_overflow = reader_.overflow;
    msg.rx_bad_frame = reader_.bad_frame;
    msg.tx_dropped = tx_dropped_;
    msg.tick_overruns = tick_overruns_;
    uint8_t out[Telemetry::PAYLOAD_SIZE];
    encode(msg, out);
    send(MSG_TELEMETRY, out, sizeof out);
}

// The one fault path: every blower off, setpoints to 0, a zero calibration aborted, the bit latched, and
// a FAULT frame sent the first time this bit latches.
void Controller::latch_fault(uint8_t bit) {
    uint16_t mask = (uint16_t)1 << bit;
    bool new_fault = !(fault_flags_ & mask);
    fault_flags_ |= mask;
    vent();
    if (zero_ticks_left_) {
        zero_ticks_left_ = 0;
        reply(MSG_ZERO_SENSORS, zero_seq_, STATUS_FAULT_LATCHED);
    }
    if (!new_fault) return;
    Fault msg;
    msg.time_ms = time_ms_;
    msg.fault_bit = bit;
    msg.fault_flags = fault_flags_;
    for (uint8_t i = 0; i < CHAMBERS; ++i) msg.pressure_pa[i] = pressure_pa_[i];
    uint8_t out[Fault::PAYLOAD_SIZE];
    encode(msg, out);
    send(MSG_FAULT, out, sizeof out);
}

// Whether a latched fault's cause persists: a sensor out of band or a chamber above its limit. A leak, a dead
// host or a watchdog reset leave nothing to observe once the blowers are off (a leak that persists trips again
// when the host re-inflates).
bool Controller::fault_cause_present() const {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (!sensor_in_range(counts_x16_[i])) return true;
        if (pressure_pa_[i] > max_pressure_pa_[i]) return true;
    }
    return false;
}

// Setpoints to 0 and every blower disconnected at once (not waiting for the next tick).
void Controller::vent() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        setpoint_pa_[i] = 0;
        drive_[i] = 0;
        pid_[i].reset(pressure_pa_[i]);
    }
}

// Frame and send one message; count it when the transport has no room.
void Controller::send(uint8_t msg_id, const uint8_t* payload, uint8_t payload_len) {
    uint8_t frame[MAX_FRAME_BYTES];
    uint8_t len = frame_encode(msg_id, tx_seq_++, payload, payload_len, frame);
    if (!send_frame_ || !send_frame_(frame, len, send_context_)) ++tx_dropped_;
}

// ACK for OK and CLAMPED, NACK for every other status.
void Controller::reply(uint8_t ref_msg_id, uint8_t ref_seq, uint8_t status) {
    uint8_t out[Ack::PAYLOAD_SIZE];
    out[0] = ref_msg_id;
    out[1] = ref_seq;
    out[2] = status;
    send(status <= STATUS_CLAMPED ? MSG_ACK : MSG_NACK, out, sizeof out);
}

}  // namespace core
