// The board's state machine: sessions, commands, the control tick, telemetry and the one latched fault path.
// Hardware-independent: the AVR layer feeds it received bytes and ADC sums and applies its drive levels.
#pragma once
#include <stdint.h>

#include "config.h"
#include "frame.h"
#include "motion.h"
#include "pid.h"
#include "protocol_generated.h"
#include "settings.h"

namespace core {

// Sends one whole wire frame; returns false when there is no room for it now (the frame is then dropped).
typedef bool (*SendFrame)(const uint8_t* frame, uint8_t len, void* context);

// ADC readings gathered during one tick: the sum of `count` conversions per chamber (a count of 0 is a stalled
// ADC), and one conversion of the internal 1.1 V reference against AVcc (0 when none was taken this tick).
struct AdcTick {
    uint16_t sum[CHAMBERS];
    uint8_t count[CHAMBERS];
    uint16_t bandgap_counts;
};

class Controller {
public:
    // Start a freshly constructed controller in the safe state: blowers off, no session, the stored settings
    // (a block of SETTINGS_BYTES read from EEPROM, or 0 for none) or the defaults; a watchdog reset latches
    // its fault at once.
    void init(uint8_t board, uint8_t reset_cause, SendFrame send, void* context, const uint8_t* stored = 0);

    // Take one received byte; a completed valid frame is acted on at once.
    void receive(uint8_t byte);

    // One control step with this tick's ADC readings and motion inputs; missed_ticks says how many ticks the loop
    // skipped. At a window's start (motion.window_start) step_plan() is then the stepper outputs of the next one.
    void tick(const AdcTick& adc, uint16_t missed_ticks, const MotionSample& motion);

    // Drive level of a chamber, 0..65535 for 0..1; 0 means the blower pin is disconnected.
    uint16_t drive(uint8_t chamber) const { return drive_[chamber]; }
    // The steps of the next tick, and which stepper drivers are enabled now (bit n: axis n; applied at once, so
    // that a fault or a refused HELLO releases them without waiting for a tick).
    const StepPlan& step_plan() const { return motion_.plan(); }
    uint8_t motion_enabled_mask() const { return motion_.enabled_mask(); }
    const Motion& motion() const { return motion_; }
    // Set by TEST_HANG after its ACK: the AVR layer stops the blowers and stops kicking the watchdog.
    bool hang_requested() const { return hang_requested_; }
    uint32_t time_ms() const { return time_ms_; }
    uint16_t fault_flags() const { return fault_flags_; }
    bool session_open() const { return session_open_; }
    int16_t pressure_pa(uint8_t chamber) const { return pressure_pa_[chamber]; }
    int16_t setpoint_pa(uint8_t chamber) const { return setpoint_pa_[chamber]; }
    int16_t max_pressure_pa(uint8_t chamber) const { return max_pressure_pa_[chamber]; }
    int16_t zero_x16(uint8_t chamber) const { return zero_x16_[chamber]; }
    uint16_t telemetry_period_ms() const { return telemetry_period_ms_; }
    uint16_t host_deadline_ms() const { return host_deadline_ms_; }
    uint8_t chamber_state(uint8_t chamber) const;
    const Pid& pid(uint8_t chamber) const { return pid_[chamber]; }
    const FrameReader& reader() const { return reader_; }
    uint16_t tx_dropped() const { return tx_dropped_; }
    uint8_t config_source() const { return config_source_; }
    uint8_t zero_source(uint8_t chamber) const { return zero_source_[chamber]; }
    int16_t ceiling_zero_x16(uint8_t chamber) const { return ceiling_zero_x16_[chamber]; }
    uint16_t supply_mv() const;
    // Bumped whenever a persistent setting changes; the AVR layer writes settings() to EEPROM when it moves.
    uint16_t settings_generation() const { return settings_generation_; }
    void settings(uint8_t out[SETTINGS_BYTES]) const;
    // The status LED: a short blink each second when idle, on while a session is open, and with a fault
    // latched its blink code (fault_blink_code): that many 200 ms blinks 200 ms apart, then 1.6 s dark, repeated
    // (blink_code_on: whether the LED is lit at board time `time_ms`).
    bool status_led_on() const;
    static uint8_t fault_blink_code(uint16_t fault_flags);
    static bool blink_code_on(uint8_t code, uint32_t time_ms);

private:
    void handle_frame();
    void on_hello(const uint8_t* payload);
    void on_set_setpoints(uint8_t seq, const uint8_t* payload);
    void on_set_pid(uint8_t seq, const uint8_t* payload);
    void on_set_config(uint8_t seq, const uint8_t* payload);
    void on_clear_fault(uint8_t seq);
    void on_vent(uint8_t seq);
    void on_zero_sensors(uint8_t seq);
    void on_test_hang(uint8_t seq, const uint8_t* payload);
    void on_motion_config(uint8_t seq, const uint8_t* payload);
    void on_move_to(uint8_t seq, const uint8_t* payload);
    void on_home(uint8_t seq, const uint8_t* payload);
    void on_motion_stop(uint8_t seq, const uint8_t* payload);

    void read_sensors(const AdcTick& adc);
    void check_supply(uint16_t bandgap_counts);
    void check_safety();
    void check_leak(uint8_t chamber);
    void check_plausible(uint8_t chamber);
    bool above_ceiling(uint8_t chamber) const;
    void track_settling();
    void start_zeroing(bool by_host, uint8_t seq);
    void run_zeroing();
    void end_zeroing(uint8_t status);
    void accept_zero(uint8_t chamber, int16_t zero_x16, uint8_t source);
    void send_board_info();
    void run_control();
    bool send_telemetry();
    bool send_motion_status();
    bool send_motion_info();

    void latch_fault(uint8_t bit);
    bool fault_cause_present() const;
    void vent();
    bool send(uint8_t msg_id, const uint8_t* payload, uint8_t payload_len);
    void reply(uint8_t ref_msg_id, uint8_t ref_seq, uint8_t status);

    FrameReader reader_;
    uint8_t config_source_ = proto::CONFIG_SOURCE_DEFAULTS;
    uint16_t settings_generation_ = 0;
    Pid pid_[CHAMBERS];
    SendFrame send_frame_ = 0;
    void* send_context_ = 0;
    uint8_t board_ = 0;
    uint8_t reset_cause_ = 0;

    uint32_t time_ms_ = 0;
    uint32_t last_rx_ms_ = 0;
    uint32_t last_telemetry_ms_ = 0;
    uint16_t telemetry_period_ms_ = DEFAULT_TELEMETRY_PERIOD_MS;
    uint16_t host_deadline_ms_ = DEFAULT_HOST_DEADLINE_MS;
    bool session_open_ = false;
    bool hang_requested_ = false;
    uint8_t tx_seq_ = 0;
    uint16_t tx_dropped_ = 0;
    uint16_t tick_overruns_ = 0;

    uint16_t fault_flags_ = 0;
    int16_t setpoint_pa_[CHAMBERS] = {0, 0, 0};
    int16_t max_pressure_pa_[CHAMBERS] = {DEFAULT_MAX_PRESSURE_PA, DEFAULT_MAX_PRESSURE_PA, DEFAULT_MAX_PRESSURE_PA};
    int16_t zero_x16_[CHAMBERS] = {0, 0, 0};    // sensor reading at 0 Pa, sixteenths of a count
    int16_t counts_x16_[CHAMBERS] = {0, 0, 0};  // latest averaged reading, sixteenths of a count
    int16_t pressure_pa_[CHAMBERS] = {0, 0, 0};
    uint8_t bad_ticks_[CHAMBERS] = {0, 0, 0};
    uint16_t leak_ticks_[CHAMBERS] = {0, 0, 0};  // ticks in a row at the drive ceiling and far below the setpoint
    uint16_t drive_[CHAMBERS] = {0, 0, 0};

    bool stalled_[CHAMBERS] = {false, false, false};  // no conversion in the last tick
    uint16_t implausible_ticks_[CHAMBERS] = {0, 0, 0};  // ticks in a row under high drive, starved
    int16_t implausible_ref_pa_[CHAMBERS] = {0, 0, 0};  // the lowest reading since that run began
    uint16_t bandgap_counts_ = 0;  // the latest measurement of the 1.1 V reference (0: none yet)
    uint8_t supply_low_ticks_ = 0;

    // Zero: the readings must have stayed within ZERO_STABLE_X16 of settle_ref_x16_ with every blower off for
    // settled_ticks_; ceiling_zero_x16_ is what the ceiling is checked against (accept_zero).
    uint16_t settled_ticks_ = 0;
    int16_t settle_ref_x16_[CHAMBERS] = {0, 0, 0};
    int16_t ceiling_zero_x16_[CHAMBERS] = {0, 0, 0};
    uint8_t zero_source_[CHAMBERS] = {0, 0, 0};
    bool boot_zero_pending_ = true;  // until the first measured zero or the first setpoint
    bool zero_by_host_ = false;
    uint8_t zero_ticks_left_ = 0;  // > 0 while a zero is measured
    uint8_t zero_seq_ = 0;
    int32_t zero_sum_x16_[CHAMBERS] = {0, 0, 0};

    // The last acknowledged command's id, seq and status: the same id and seq again is a retransmission,
    // answered from here and not executed twice.
    bool reply_cached_ = false;
    uint8_t cached_msg_id_ = 0;
    uint8_t cached_seq_ = 0;
    uint8_t cached_status_ = 0;

    // The scanner's stepper axes; their status is sent every MOTION_STATUS_PERIOD_MS and on a change, their
    // configuration (MOTION_INFO) once for each bit of motion_info_pending_, each in a tick without telemetry.
    Motion motion_;
    uint32_t last_motion_status_ms_ = 0;
    uint8_t motion_info_pending_ = 0;
};

}  // namespace core
