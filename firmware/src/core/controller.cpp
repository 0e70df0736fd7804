#include "controller.h"

#include "sensor.h"

namespace core {

using namespace proto;

// Safe start: every chamber off, with the stored settings when a good block is given, else the defaults and
// the nominal sensor zero.
void Controller::init(uint8_t board, uint8_t reset_cause, SendFrame send, void* context, const uint8_t* stored) {
    board_ = board;
    reset_cause_ = reset_cause;
    send_frame_ = send;
    send_context_ = context;
    Settings settings;
    PidGains gains = {DEFAULT_KP_PER_KPA, DEFAULT_KI_PER_KPA_S, DEFAULT_KD_S_PER_KPA, 65535};
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        settings.zero_x16[i] = 0;
        settings.gains[i] = gains;
        settings.max_pressure_pa[i] = DEFAULT_MAX_PRESSURE_PA;
    }
    config_source_ = stored ? settings_decode(stored, settings) : (uint8_t)CONFIG_SOURCE_DEFAULTS;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        pid_[i].init(settings.gains[i]);
        max_pressure_pa_[i] = settings.max_pressure_pa[i];
        zero_x16_[i] = NOMINAL_ZERO_X16;
        ceiling_zero_x16_[i] = NOMINAL_ZERO_X16 - ZERO_MAX_OFFSET_X16;  // the worst part the datasheet allows
        zero_source_[i] = ZERO_SOURCE_NOMINAL;
        if (settings.zero_x16[i]) accept_zero(i, settings.zero_x16[i], ZERO_SOURCE_STORED);
        counts_x16_[i] = zero_x16_[i];
        settle_ref_x16_[i] = zero_x16_[i];
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
        send(MSG_PONG, out, sizeof out);
        return;
    }
    if (id == MSG_VENT) return on_vent(seq);
    if (!session_open_) return reply(id, seq, STATUS_NO_SESSION);
    if (reply_cached_ && id == cached_msg_id_ && seq == cached_seq_) return reply(id, seq, cached_status_);
    if (zero_ticks_left_ && zero_by_host_ && id == MSG_ZERO_SENSORS && seq == zero_seq_) return;  // ACK comes
    switch (id) {
    case MSG_SET_SETPOINTS: return on_set_setpoints(seq, payload);
    case MSG_SET_PID: return on_set_pid(seq, payload);
    case MSG_SET_CONFIG: return on_set_config(seq, payload);
    case MSG_CLEAR_FAULT: return on_clear_fault(seq);
    case MSG_ZERO_SENSORS: return on_zero_sensors(seq);
    case MSG_TEST_HANG: return on_test_hang(seq, payload);
    case MSG_MOTION_CONFIG: return on_motion_config(seq, payload);
    case MSG_MOVE_TO: return on_move_to(seq, payload);
    case MSG_HOME: return on_home(seq, payload);
    case MSG_MOTION_STOP: return on_motion_stop(seq, payload);
    default: return;
    }
}

// Answer HELLO with who we are; open the session only if both sides were built from the same spec. A refused
// HELLO also vents and halts the motion: without a session nothing supervises the blowers or the steppers (no
// host deadline).
void Controller::on_hello(const uint8_t* payload) {
    Hello hello;
    decode(hello, payload);
    bool match = hello.spec_hash == SPEC_HASH && hello.protocol_version == PROTOCOL_VERSION;
    session_open_ = match;
    reply_cached_ = false;  // a new session numbers its commands afresh
    if (!match) {
        vent();
        motion_.halt();
    }
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
    if (!match) return;
    send_board_info();
    for (uint8_t n = 0; n < AXES; ++n)
        if (motion_.axis(n).configured()) motion_info_pending_ |= (uint8_t)(1u << n);
}

// What HELLO_REPLY's fixed layout cannot carry: where the settings and the zeros came from, and the supply.
void Controller::send_board_info() {
    BoardInfo info;
    info.config_source = config_source_;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        info.zero_source[i] = zero_source_[i];
        info.zero_offset_pa[i] = sensor_x16_to_pa(zero_x16_[i], NOMINAL_ZERO_X16);
    }
    info.supply_mv = supply_mv();
    uint8_t out[BoardInfo::PAYLOAD_SIZE];
    encode(info, out);
    send(MSG_BOARD_INFO, out, sizeof out);
}

// Absolute setpoints for all chambers, all or nothing; a chamber switched on starts its PID from rest.
void Controller::on_set_setpoints(uint8_t seq, const uint8_t* payload) {
    if (fault_flags_) return reply(MSG_SET_SETPOINTS, seq, STATUS_FAULT_LATCHED);
    if (zero_ticks_left_ && zero_by_host_) return reply(MSG_SET_SETPOINTS, seq, STATUS_BUSY);
    SetSetpoints msg;
    decode(msg, payload);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (msg.setpoint_pa[i] < 0 || msg.setpoint_pa[i] > max_pressure_pa_[i])
            return reply(MSG_SET_SETPOINTS, seq, STATUS_BAD_VALUE);
    }
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (setpoint_pa_[i] == 0 && msg.setpoint_pa[i] > 0) pid_[i].reset(pressure_pa_[i]);
        if (msg.setpoint_pa[i] > 0) {
            boot_zero_pending_ = false;  // the host has taken over the chambers: no zero of its own now
            zero_ticks_left_ = 0;
        }
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
    ++settings_generation_;
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

// Start averaging each sensor's zero, but only on chambers that have been vented and still long enough; the
// ACK (or NACK) comes when it is done.
void Controller::on_zero_sensors(uint8_t seq) {
    if (fault_flags_) return reply(MSG_ZERO_SENSORS, seq, STATUS_FAULT_LATCHED);
    if (zero_ticks_left_) return reply(MSG_ZERO_SENSORS, seq, STATUS_BUSY);
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (setpoint_pa_[i] != 0 || drive_[i] != 0) return reply(MSG_ZERO_SENSORS, seq, STATUS_NOT_VENTED);
    }
    if (settled_ticks_ < ZERO_SETTLE_TICKS) return reply(MSG_ZERO_SENSORS, seq, STATUS_NOT_SETTLED);
    start_zeroing(true, seq);
}

void Controller::start_zeroing(bool by_host, uint8_t seq) {
    zero_by_host_ = by_host;
    zero_ticks_left_ = ZERO_TICKS;
    zero_seq_ = seq;
    for (uint8_t i = 0; i < CHAMBERS; ++i) zero_sum_x16_[i] = 0;
}

// Bench-only hang: acknowledged first, then the AVR layer stops kicking the watchdog.
// A production build has no TEST_HANG: every magic is a bad one.
void Controller::on_test_hang(uint8_t seq, const uint8_t* payload) {
#ifdef PHANTOM_BENCH
    bool bench_build = true;
#else
    bool bench_build = false;
#endif
    if (!bench_build || get_u32(payload) != TEST_HANG_MAGIC) return reply(MSG_TEST_HANG, seq, STATUS_BAD_MAGIC);
    vent();
    motion_.halt();
    reply(MSG_TEST_HANG, seq, STATUS_OK);
    hang_requested_ = true;
}

// One axis's configuration; the board answers with MOTION_INFO (in a later tick) once it is taken.
void Controller::on_motion_config(uint8_t seq, const uint8_t* payload) {
    MotionConfig msg;
    decode(msg, payload);
    if (msg.axis >= AXES) return reply(MSG_MOTION_CONFIG, seq, STATUS_BAD_VALUE);
    AxisConfig config = {msg.steps_per_rev,  msg.max_speed_mdeg_s, msg.max_accel_mdeg_s2, msg.min_angle_mdeg,
                         msg.max_angle_mdeg, msg.home_speed_mdeg_s, msg.options};
    uint8_t status = motion_.axis(msg.axis).configure(config);
    if (status == STATUS_OK) motion_info_pending_ |= (uint8_t)(1u << msg.axis);
    reply(MSG_MOTION_CONFIG, seq, status);
}

// Motion commands are refused while a fault is latched (it has halted every axis), except MOTION_STOP.
void Controller::on_move_to(uint8_t seq, const uint8_t* payload) {
    MoveTo msg;
    decode(msg, payload);
    if (msg.axis >= AXES) return reply(MSG_MOVE_TO, seq, STATUS_BAD_VALUE);
    if (fault_flags_) return reply(MSG_MOVE_TO, seq, STATUS_FAULT_LATCHED);
    reply(MSG_MOVE_TO, seq, motion_.move_to(msg.axis, msg.angle_mdeg));
}

void Controller::on_home(uint8_t seq, const uint8_t* payload) {
    Home msg;
    decode(msg, payload);
    if (msg.axis >= AXES) return reply(MSG_HOME, seq, STATUS_BAD_VALUE);
    if (fault_flags_) return reply(MSG_HOME, seq, STATUS_FAULT_LATCHED);
    reply(MSG_HOME, seq, motion_.home(msg.axis, msg.method, msg.angle_mdeg));
}

void Controller::on_motion_stop(uint8_t seq, const uint8_t* payload) {
    MotionStop msg;
    decode(msg, payload);
    if (msg.release > 1) return reply(MSG_MOTION_STOP, seq, STATUS_BAD_VALUE);
    motion_.stop(msg.release == 1);
    reply(MSG_MOTION_STOP, seq, STATUS_OK);
}

// One tick: measure, check every fault, then zero or control, move the steppers on (planning their next window
// when one starts), then maybe report: at most one frame a tick, telemetry first, then the motion status, then a
// motion configuration.
void Controller::tick(const AdcTick& adc, uint16_t missed_ticks, const MotionSample& motion) {
    time_ms_ += (uint32_t)TICK_MS * (1u + missed_ticks);
    tick_overruns_ = (uint16_t)(tick_overruns_ + missed_ticks);
    read_sensors(adc);
    check_supply(adc.bandgap_counts);
    check_safety();
    track_settling();
    if (boot_zero_pending_ && !zero_ticks_left_ && settled_ticks_ >= ZERO_SETTLE_TICKS) start_zeroing(false, 0);
    if (zero_ticks_left_) run_zeroing();
    run_control();
    motion_.tick(motion);
    if (!send_telemetry() && !send_motion_status()) send_motion_info();
}

// Average this tick's ADC conversions; a chamber without a new conversion keeps its last reading, marked
// stalled (a bad sample: it drives nothing and counts towards SENSOR_n).
void Controller::read_sensors(const AdcTick& adc) {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        stalled_[i] = adc.count[i] == 0;
        if (stalled_[i]) continue;
        counts_x16_[i] = sensor_average_x16(adc.sum[i], adc.count[i]);
        pressure_pa_[i] = sensor_x16_to_pa(counts_x16_[i], zero_x16_[i]);
    }
}

// The smallest reading above the ceiling zero that sensor_x16_to_pa turns into more than PRESSURE_CEILING_PA:
// the ceiling compared in counts, without a multiplication per chamber and tick.
static const int16_t CEILING_X16 =
    (int16_t)(((int32_t)(PRESSURE_CEILING_PA + 1) * 4096 - 2048 + PA_PER_COUNT_X16_Q12 - 1) / PA_PER_COUNT_X16_Q12);

bool Controller::above_ceiling(uint8_t chamber) const {
    return counts_x16_[chamber] - ceiling_zero_x16_[chamber] >= CEILING_X16;
}

// AVcc from the 1.1 V reference read against it (counts = 1100 mV * 1024 / AVcc): the supply is below
// SUPPLY_MIN_MV when the count is above 1100 * 1024 / SUPPLY_MIN_MV. SUPPLY_BAD_TICKS measured ticks in a row
// below it latch SUPPLY. A tick without a measurement neither counts nor resets.
static const uint16_t SUPPLY_MAX_BANDGAP_COUNTS = (uint16_t)(1126400UL / SUPPLY_MIN_MV);

uint16_t Controller::supply_mv() const {
    return bandgap_counts_ ? (uint16_t)(1126400UL / bandgap_counts_) : 0;
}
void Controller::check_supply(uint16_t bandgap_counts) {
    if (bandgap_counts == 0) return;
    bandgap_counts_ = bandgap_counts;
    if (bandgap_counts <= SUPPLY_MAX_BANDGAP_COUNTS) {  // a comparison, not a 32-bit division, every tick
        supply_low_ticks_ = 0;
        return;
    }
    if (supply_low_ticks_ < SUPPLY_BAD_TICKS) ++supply_low_ticks_;
    if (supply_low_ticks_ >= SUPPLY_BAD_TICKS) latch_fault(FAULT_SUPPLY);
}

// Sensor band (several ticks in a row), over-pressure and leak (on a valid reading), the dead-host deadline.
void Controller::check_safety() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        if (stalled_[i] || !sensor_in_range(counts_x16_[i])) {
            if (bad_ticks_[i] < SENSOR_BAD_TICKS) ++bad_ticks_[i];
            if (bad_ticks_[i] >= SENSOR_BAD_TICKS) latch_fault((uint8_t)(FAULT_SENSOR_0 + i));
            leak_ticks_[i] = 0;
            implausible_ticks_[i] = 0;
            continue;
        }
        bad_ticks_[i] = 0;
        if (pressure_pa_[i] > max_pressure_pa_[i] || above_ceiling(i))
            latch_fault((uint8_t)(FAULT_OVERPRESSURE_0 + i));
        check_leak(i);
        check_plausible(i);
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

// A chamber whose reading does not respond to its blower: at least PLAUSIBLE_MIN_DRIVE while it reads more than
// LEAK_MIN_ERROR_PA below its setpoint, and in PLAUSIBLE_TICKS of that the reading never rose
// PLAUSIBLE_MIN_CHANGE_PA above its lowest since the push began. Its sensor does not see the chamber (a tube off,
// a stuck sensor), or the chamber is open to the air: either way the blower cannot raise the reading. A push
// whose reading has risen is left to the leak rule (can rise, cannot reach or hold) until it ends.
void Controller::check_plausible(uint8_t chamber) {
    static const uint16_t RESPONDED = 0xFFFF;
    int16_t setpoint_pa = setpoint_pa_[chamber];
    int16_t pressure_pa = pressure_pa_[chamber];
    bool pushing = setpoint_pa > 0 && drive_[chamber] >= PLAUSIBLE_MIN_DRIVE &&
                   pressure_pa < setpoint_pa - LEAK_MIN_ERROR_PA;
    uint16_t& ticks = implausible_ticks_[chamber];
    if (!pushing) {
        ticks = 0;
        return;
    }
    if (ticks == 0) {
        implausible_ref_pa_[chamber] = pressure_pa;
        ticks = 1;
        return;
    }
    if (ticks == RESPONDED) return;
    if (pressure_pa < implausible_ref_pa_[chamber]) implausible_ref_pa_[chamber] = pressure_pa;
    if (pressure_pa - implausible_ref_pa_[chamber] >= PLAUSIBLE_MIN_CHANGE_PA) {
        ticks = RESPONDED;
        return;
    }
    if (++ticks < PLAUSIBLE_TICKS) return;
    ticks = 0;
    latch_fault((uint8_t)(FAULT_IMPLAUSIBLE_0 + chamber));
}

// Count the ticks every blower has been off and every reading within ZERO_STABLE_X16 of where the count began.
void Controller::track_settling() {
    bool still = true;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        int16_t moved = (int16_t)(counts_x16_[i] - settle_ref_x16_[i]);
        if (drive_[i] != 0 || setpoint_pa_[i] != 0 || bad_ticks_[i] || moved > ZERO_STABLE_X16 ||
            moved < -ZERO_STABLE_X16)
            still = false;
    }
    if (still) {
        if (settled_ticks_ < 0xFFFF) ++settled_ticks_;
        return;
    }
    settled_ticks_ = 0;
    for (uint8_t i = 0; i < CHAMBERS; ++i) settle_ref_x16_[i] = counts_x16_[i];
    if (zero_ticks_left_) end_zeroing(STATUS_NOT_SETTLED);
}

// Accumulate the zero readings; at the end store them all, or refuse them all if one is out of the datasheet's
// offset tolerance.
void Controller::run_zeroing() {
    for (uint8_t i = 0; i < CHAMBERS; ++i) zero_sum_x16_[i] += counts_x16_[i];
    if (--zero_ticks_left_) return;
    int16_t zero[CHAMBERS];
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        zero[i] = (int16_t)((zero_sum_x16_[i] + ZERO_TICKS / 2) / ZERO_TICKS);
        int16_t offset = (int16_t)(zero[i] - NOMINAL_ZERO_X16);
        if (offset > ZERO_MAX_OFFSET_X16 || offset < -ZERO_MAX_OFFSET_X16) return end_zeroing(STATUS_ZERO_OUT_OF_RANGE);
    }
    uint8_t source = zero_by_host_ ? ZERO_SOURCE_HOST : ZERO_SOURCE_BOOT;
    for (uint8_t i = 0; i < CHAMBERS; ++i) accept_zero(i, zero[i], source);
    ++settings_generation_;
    end_zeroing(STATUS_OK);
}

// Stop a zero measurement; the host hears how it ended if it asked for it. A boot zero that ends on anything
// but OK is tried again once the readings settle (unless a setpoint came first).
void Controller::end_zeroing(uint8_t status) {
    zero_ticks_left_ = 0;
    if (status == STATUS_OK) boot_zero_pending_ = false;
    if (zero_by_host_) reply(MSG_ZERO_SENSORS, zero_seq_, status);
}

// Use a zero. The over-pressure ceiling is checked against a zero that no later zero can raise: until the board
// has measured its own zero at start-up (blowers off since reset, readings stable), the lowest the datasheet
// allows; from then on the lowest of that, the nominal zero and every zero since. A zero taken with air left in a
// chamber (which reads high) can then only make the ceiling trip earlier, never later.
void Controller::accept_zero(uint8_t chamber, int16_t zero_x16, uint8_t source) {
    zero_x16_[chamber] = zero_x16;
    zero_source_[chamber] = source;
    int16_t& ceiling_zero = ceiling_zero_x16_[chamber];
    if (source == ZERO_SOURCE_BOOT && ceiling_zero == NOMINAL_ZERO_X16 - ZERO_MAX_OFFSET_X16)
        ceiling_zero = zero_x16 < NOMINAL_ZERO_X16 ? zero_x16 : NOMINAL_ZERO_X16;
    else if (zero_x16 < ceiling_zero)
        ceiling_zero = zero_x16;
    pressure_pa_[chamber] = sensor_x16_to_pa(counts_x16_[chamber], zero_x16_[chamber]);
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

// Stream one TELEMETRY frame per period while a session is open; whether one was sent.
bool Controller::send_telemetry() {
    if (!session_open_ || telemetry_period_ms_ == 0) return false;
    if (time_ms_ - last_telemetry_ms_ < telemetry_period_ms_) return false;
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
    return true;
}

// MOTION_STATUS every MOTION_STATUS_PERIOD_MS while a session is open and an axis is configured, and at once
// after a command or a change of state; whether one was sent.
bool Controller::send_motion_status() {
    if (!session_open_ || !motion_.any_configured()) return false;
    if (!motion_.changed() && time_ms_ - last_motion_status_ms_ < MOTION_STATUS_PERIOD_MS) return false;
    last_motion_status_ms_ = time_ms_;
    motion_.clear_changed();
    MotionStatus msg;
    msg.time_ms = time_ms_;
    for (uint8_t n = 0; n < AXES; ++n) {
        const Axis& axis = motion_.axis(n);
        msg.state[n] = axis.state();
        msg.flags[n] = axis.flags();
        msg.result[n] = axis.result();
        msg.position_steps[n] = axis.position_steps();
        msg.position_mdeg[n] = axis.position_mdeg();
        msg.target_mdeg[n] = axis.target_mdeg();
        msg.velocity_mdeg_s[n] = axis.velocity_mdeg_s();
    }
    uint8_t out[MotionStatus::PAYLOAD_SIZE];
    encode(msg, out);
    send(MSG_MOTION_STATUS, out, sizeof out);
    return true;
}

// One pending MOTION_INFO (an axis's configuration as held), lowest axis first; whether one was sent. It is sent
// once, so it stays pending until the transport took it (a frame that finds the UART's ring full goes next time).
bool Controller::send_motion_info() {
    if (!motion_info_pending_) return false;
    if (!session_open_) motion_info_pending_ = 0;
    for (uint8_t n = 0; n < AXES; ++n) {
        if (!(motion_info_pending_ & (1u << n))) continue;
        const AxisConfig& c = motion_.axis(n).config();
        MotionInfo msg = {n, c.steps_per_rev, c.max_speed_mdeg_s, c.max_accel_mdeg_s2, c.min_angle_mdeg,
                          c.max_angle_mdeg, c.home_speed_mdeg_s, c.options};
        uint8_t out[MotionInfo::PAYLOAD_SIZE];
        encode(msg, out);
        if (send(MSG_MOTION_INFO, out, sizeof out)) motion_info_pending_ &= (uint8_t)~(1u << n);
        return true;
    }
    return false;
}

// The one fault path: every blower off, setpoints to 0, a zero calibration aborted, every stepper halted and its
// driver released, the bit latched, and a FAULT frame sent the first time this bit latches.
void Controller::latch_fault(uint8_t bit) {
    uint16_t mask = (uint16_t)1 << bit;
    bool new_fault = !(fault_flags_ & mask);
    fault_flags_ |= mask;
    vent();
    motion_.halt();
    if (zero_ticks_left_) end_zeroing(STATUS_FAULT_LATCHED);
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
        if (stalled_[i] || !sensor_in_range(counts_x16_[i])) return true;
        if (pressure_pa_[i] > max_pressure_pa_[i] || above_ceiling(i)) return true;
    }
    return supply_low_ticks_ != 0;
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
bool Controller::send(uint8_t msg_id, const uint8_t* payload, uint8_t payload_len) {
    uint8_t frame[MAX_FRAME_BYTES];
    uint8_t len = frame_encode(msg_id, tx_seq_++, payload, payload_len, frame);
    if (send_frame_ && send_frame_(frame, len, send_context_)) return true;
    ++tx_dropped_;
    return false;
}

// ACK for OK and CLAMPED, NACK for every other status; remembered for a retransmission of the same command.
void Controller::reply(uint8_t ref_msg_id, uint8_t ref_seq, uint8_t status) {
    reply_cached_ = true;
    cached_msg_id_ = ref_msg_id;
    cached_seq_ = ref_seq;
    cached_status_ = status;
    uint8_t out[Ack::PAYLOAD_SIZE];
    out[0] = ref_msg_id;
    out[1] = ref_seq;
    out[2] = status;
    send(status <= STATUS_CLAMPED ? MSG_ACK : MSG_NACK, out, sizeof out);
}

}  // namespace core

namespace core {

// The persistent settings as they are now.
void Controller::settings(uint8_t out[SETTINGS_BYTES]) const {
    Settings s;
    for (uint8_t i = 0; i < CHAMBERS; ++i) {
        s.zero_x16[i] = zero_source_[i] == ZERO_SOURCE_NOMINAL ? 0 : zero_x16_[i];
        s.gains[i] = pid_[i].gains();
        s.max_pressure_pa[i] = max_pressure_pa_[i];
    }
    settings_encode(s, out);
}

// Blink codes, counted by a person: 1 over-pressure, 2 sensor, 3 implausible reading, 4 leak, 5 dead host,
// 6 watchdog reset, 7 supply; the first in this order that is latched.
uint8_t Controller::fault_blink_code(uint16_t fault_flags) {
    static const uint16_t groups[] = {
        (1u << FAULT_OVERPRESSURE_0) | (1u << FAULT_OVERPRESSURE_1) | (1u << FAULT_OVERPRESSURE_2),
        (1u << FAULT_SENSOR_0) | (1u << FAULT_SENSOR_1) | (1u << FAULT_SENSOR_2),
        (1u << FAULT_IMPLAUSIBLE_0) | (1u << FAULT_IMPLAUSIBLE_1) | (1u << FAULT_IMPLAUSIBLE_2),
        (1u << FAULT_LEAK_0) | (1u << FAULT_LEAK_1) | (1u << FAULT_LEAK_2),
        1u << FAULT_DEAD_HOST,
        1u << FAULT_WATCHDOG_RESET,
        1u << FAULT_SUPPLY,
    };
    for (uint8_t k = 0; k < sizeof groups / sizeof groups[0]; ++k)
        if (fault_flags & groups[k]) return (uint8_t)(k + 1);
    return 0;
}

// `code` blinks of 200 ms on / 200 ms off, then 1.6 s dark from the last blink's end (8 times the gap between
// blinks), over and over: a repeat of 400 * code + 1400 ms (1.8 s for code 1, 4.2 s for code 7; the 16-bit
// arithmetic holds for codes up to 160).
bool Controller::blink_code_on(uint8_t code, uint32_t time_ms) {
    uint16_t phase_ms = (uint16_t)(time_ms % (400u * code + 1400u));
    return phase_ms < 400u * code && phase_ms % 400u < 200u;
}

// Fault: its blink code. No fault: on with a session, else a 50 ms blink each second (the firmware runs).
bool Controller::status_led_on() const {
    uint8_t code = fault_blink_code(fault_flags_);
    if (code) return blink_code_on(code, time_ms_);
    if (session_open_) return true;
    return time_ms_ % 1000u < 50u;
}

}  // namespace core
