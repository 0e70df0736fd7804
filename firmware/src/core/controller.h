// The board's state machine: sessions, commands, the control tick, telemetry and the one latched fault path.
// Hardware-independent: the AVR layer feeds it received bytes and ADC sums and applies its drive levels.
#pragma once
#include <stdint.h>

#include "config.h"
#include "frame.h"
#include "pid.h"
#include "protocol_generated.h"

namespace core {

// Sends one whole wire frame; returns false when there is no room for it now (the frame is then dropped).
typedef bool (*SendFrame)(const uint8_t* frame, uint8_t len, void* context);

// ADC readings gathered during one tick: the sum of `count` conversions per chamber.
struct AdcTick {
    uint16_t sum[CHAMBERS];
    uint8_t count[CHAMBERS];
};

class Controller {
public:
    // Start a freshly constructed controller in the safe state: blowers off, no session, default gains;
    // a watchdog reset latches its fault at once.
    void init(uint8_t board, uint8_t reset_cause, SendFrame send, void* context);

    // Take one received byte; a completed valid frame is acted on at once.
    void receive(uint8_t byte);

    // One control step with this tick's ADC readings; missed_ticks says how many ticks the loop skipped.
    void tick(const AdcTick& adc, uint16_t missed_ticks);

    // Drive level of a chamber, 0..65535 for 0..1; 0 means the blower pin is disconnected.
    uint16_t drive(uint8_t chamber) const { return drive_[chamber]; }
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

    void read_sensors(const AdcTick& adc);
    void check_safety();
    void check_leak(uint8_t chamber);
    void run_zeroing();
    void run_control();
    void send_telemetry();

    void latch_fault(uint8_t bit);
    bool fault_cause_present() const;
    void vent();
    void send(uint8_t msg_id, const uint8_t* payload, uint8_t payload_len);
    void reply(uint8_t ref_msg_id, uint8_t ref_seq, uint8_t status);

    FrameReader reader_;
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

    uint8_t zero_ticks_left_ = 0;  // > 0 while ZERO_SENSORS runs
    uint8_t zero_seq_ = 0;
    int32_t zero_sum_x16_[CHAMBERS] = {0, 0, 0};
};

}  // namespace core
