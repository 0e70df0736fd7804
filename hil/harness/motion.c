#include "motion.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "avr_ioport.h"
#include "sim_io.h"

/* Data-space addresses of PINx (DDRx and PORTx follow), the same on the ATmega328P and the ATmega2560. */
static uint16_t pin_address(char port)
{
	switch (port) {
	case 'A': return 0x20;
	case 'B': return 0x23;
	case 'C': return 0x26;
	default: return 0x29;
	}
}

static int pin_bit(const avr_t *avr, motion_pin_t pin, int offset)
{
	return (avr->data[pin_address(pin.port) + offset] >> pin.bit) & 1;
}

/* firmware/src/board_pins.h: STEP, DIR, EN, home of each axis. */
static const motion_pin_t uno_pins[MOTION_AXES][4] = {
	{{'D', 2}, {'D', 5}, {'D', 7}, {'C', 3}},
	{{'D', 4}, {'D', 6}, {'B', 0}, {'C', 4}},
};
static const motion_pin_t mega_pins[MOTION_AXES][4] = {
	{{'A', 0}, {'A', 2}, {'A', 4}, {'A', 6}},
	{{'A', 1}, {'A', 3}, {'A', 5}, {'A', 7}},
};

/* The harness's running cycle count now, inside an instruction the core is running. */
static uint64_t now_cycle(const motion_t *motion)
{
	return *motion->cycle + (motion->avr->cycle - *motion->core_cycle);
}

static void keep_min(uint64_t *minimum, uint64_t value)
{
	if (value < *minimum)
		*minimum = value;
}

int motion_enabled(const motion_axis_t *axis)
{
	const avr_t *avr = axis->motion->avr;
	return pin_bit(avr, axis->en, 1) && !pin_bit(avr, axis->en, 2);
}

/* A STEP pin changed: a rising edge is a pulse the driver takes if enabled, counted by the DIR level. */
static void on_step(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	motion_axis_t *axis = param;
	uint64_t now = now_cycle(axis->motion);
	int level = value & 1;
	if (level == axis->step_level)
		return;
	axis->step_level = level;
	if (!level) {
		keep_min(&axis->min_high, now - axis->last_rise);
		axis->last_fall = now;
		return;
	}
	if (axis->last_fall)
		keep_min(&axis->min_low, now - axis->last_fall);
	if (axis->last_rise)
		keep_min(&axis->min_interval, now - axis->last_rise);
	if (axis->last_dir_change > axis->last_rise)
		keep_min(&axis->min_setup, now - axis->last_dir_change);
	axis->last_rise = now;
	if (!motion_enabled(axis)) {
		axis->pulses_while_released++;
		return;
	}
	int direction = axis->dir_level ? 1 : -1;
	axis->steps += direction;
	axis->pulses++;
	if (axis->logged < MOTION_LOG_CAPACITY) {
		axis->log_cycle[axis->logged] = now;
		axis->log_direction[axis->logged] = (int8_t)direction;
		axis->logged++;
	}
}

/* A DIR pin changed: the time since the last rising STEP edge is the DIR hold time. */
static void on_dir(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	motion_axis_t *axis = param;
	int level = value & 1;
	if (level == axis->dir_level)
		return;
	uint64_t now = now_cycle(axis->motion);
	axis->dir_level = level;
	if (axis->last_rise)
		keep_min(&axis->min_hold, now - axis->last_rise);
	axis->last_dir_change = now;
}

void motion_reset_counters(motion_t *motion)
{
	for (int n = 0; n < MOTION_AXES; n++) {
		motion_axis_t *axis = &motion->axes[n];
		axis->pulses = axis->pulses_while_released = 0;
		axis->min_high = axis->min_low = axis->min_setup = axis->min_hold = axis->min_interval = UINT64_MAX;
		axis->logged = 0;
	}
}

void motion_attach(motion_t *motion, avr_t *avr, const uint64_t *cycle, const uint64_t *core_cycle)
{
	motion->avr = avr;
	motion->cycle = cycle;
	motion->core_cycle = core_cycle;
	const motion_pin_t (*pins)[4] = strcmp(avr->mmcu, "atmega2560") ? uno_pins : mega_pins;
	for (int n = 0; n < MOTION_AXES; n++) {
		motion_axis_t *axis = &motion->axes[n];
		axis->motion = motion;
		axis->step = pins[n][0];
		axis->dir = pins[n][1];
		axis->en = pins[n][2];
		axis->home = pins[n][3];
		axis->log_cycle = malloc(MOTION_LOG_CAPACITY * sizeof(*axis->log_cycle));
		axis->log_direction = malloc(MOTION_LOG_CAPACITY * sizeof(*axis->log_direction));
		axis->released_since_s = 0;
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(axis->step.port), axis->step.bit),
		                        on_step, axis);
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(axis->dir.port), axis->dir.bit),
		                        on_dir, axis);
	}
	motion_reset_counters(motion);
}

double motion_angle_deg(const motion_axis_t *axis)
{
	if (axis->steps_per_rev <= 0)
		return NAN;
	return axis->start_deg + (double)axis->steps * 360.0 / axis->steps_per_rev;
}

/* The external drive of a port's home inputs (both axes' switches may share a port). */
static void drive_home_inputs(motion_t *motion, char port)
{
	avr_ioport_external_t external = {.name = port, .mask = 0, .value = 0};
	for (int n = 0; n < MOTION_AXES; n++) {
		motion_axis_t *axis = &motion->axes[n];
		if (axis->home.port != port || !axis->switch_wired)
			continue;
		double angle = motion_angle_deg(axis);
		int active = !isnan(angle) && angle >= axis->switch_low_deg && angle <= axis->switch_high_deg;
		int level = active ? axis->switch_active_high : !axis->switch_active_high;
		external.mask |= 1u << axis->home.bit;
		external.value |= (unsigned)level << axis->home.bit;
		/* the PIN bit itself: a write to PORT re-raises the pins from `external`, but an unchanged IRQ value
		   (filtered) would not rewrite PIN after a reset cleared it */
		uint8_t *pin = &motion->avr->data[pin_address(port)];
		*pin = (uint8_t)((*pin & ~(1u << axis->home.bit)) | (level << axis->home.bit));
	}
	avr_ioctl(motion->avr, AVR_IOCTL_IOPORT_SET_EXTERNAL(port), &external);
}

void motion_step(motion_t *motion, double now_s)
{
	for (int n = 0; n < MOTION_AXES; n++) {
		motion_axis_t *axis = &motion->axes[n];
		if (axis->switch_wired)
			drive_home_inputs(motion, axis->home.port);
		if (motion_enabled(axis))
			axis->released_since_s = -1;
		else if (axis->released_since_s < 0)
			axis->released_since_s = now_s;
	}
}

void motion_set_switch(motion_axis_t *axis, int wired, double low_deg, double high_deg, int active_high)
{
	axis->switch_wired = wired;
	axis->switch_low_deg = low_deg;
	axis->switch_high_deg = high_deg;
	axis->switch_active_high = active_high;
	drive_home_inputs(axis->motion, axis->home.port);
	if (!wired) {
		/* an open input: what the firmware's pull-up (PORT bit) makes of it */
		avr_t *avr = axis->motion->avr;
		uint8_t *pin = &avr->data[pin_address(axis->home.port)];
		int level = pin_bit(avr, axis->home, 2);
		*pin = (uint8_t)((*pin & ~(1u << axis->home.bit)) | (level << axis->home.bit));
	}
}

long motion_write_log(const motion_axis_t *axis, const char *path)
{
	FILE *file = fopen(path, "wb");
	if (!file)
		return -1;
	for (size_t k = 0; k < axis->logged; k++) {
		uint8_t record[9];
		for (int b = 0; b < 8; b++)
			record[b] = (uint8_t)(axis->log_cycle[k] >> (8 * b));
		record[8] = (uint8_t)axis->log_direction[k];
		if (fwrite(record, sizeof(record), 1, file) != 1) {
			fclose(file);
			return -1;
		}
	}
	return fclose(file) ? -1 : (long)axis->logged;
}

static void format_angle(char *out, size_t size, double angle)
{
	if (isnan(angle))
		snprintf(out, size, "null");
	else
		snprintf(out, size, "%.9g", angle);
}

void motion_format_positions(const motion_t *motion, char *out, size_t size)
{
	size_t used = snprintf(out, size, "[");
	for (int n = 0; n < MOTION_AXES && used < size; n++) {
		const motion_axis_t *axis = &motion->axes[n];
		char angle[32];
		format_angle(angle, sizeof(angle), motion_angle_deg(axis));
		used += snprintf(out + used, size - used, "%s{\"steps\": %lld, \"angle_deg\": %s, \"enabled\": %s}",
		                 n ? ", " : "", (long long)axis->steps, angle, motion_enabled(axis) ? "true" : "false");
	}
	if (used < size)
		snprintf(out + used, size - used, "]");
}

/* A minimum in cycles as JSON: null when nothing was measured. */
static void format_cycles(char *out, size_t size, uint64_t cycles)
{
	if (cycles == UINT64_MAX)
		snprintf(out, size, "null");
	else
		snprintf(out, size, "%llu", (unsigned long long)cycles);
}

void motion_format_details(const motion_t *motion, char *out, size_t size)
{
	size_t used = snprintf(out, size, "{\"axes\": [");
	for (int n = 0; n < MOTION_AXES && used < size; n++) {
		const motion_axis_t *axis = &motion->axes[n];
		char angle[32], high[24], low[24], setup[24], hold[24], interval[24], released[32] = "null";
		format_angle(angle, sizeof(angle), motion_angle_deg(axis));
		if (axis->released_since_s >= 0)
			snprintf(released, sizeof(released), "%.9f", axis->released_since_s);
		format_cycles(high, sizeof(high), axis->min_high);
		format_cycles(low, sizeof(low), axis->min_low);
		format_cycles(setup, sizeof(setup), axis->min_setup);
		format_cycles(hold, sizeof(hold), axis->min_hold);
		format_cycles(interval, sizeof(interval), axis->min_interval);
		int home = pin_bit(motion->avr, axis->home, 0);
		used += snprintf(out + used, size - used,
		                 "%s{\"steps\": %lld, \"angle_deg\": %s, \"steps_per_rev\": %.9g, \"start_deg\": %.9g, "
		                 "\"enabled\": %s, \"dir_high\": %s, \"pulses\": %llu, \"pulses_while_released\": %llu, "
		                 "\"logged\": %zu, \"min_high_cycles\": %s, \"min_low_cycles\": %s, "
		                 "\"min_dir_setup_cycles\": %s, \"min_dir_hold_cycles\": %s, \"min_interval_cycles\": %s, "
		                 "\"released_since_s\": %s, \"switch_wired\": %s, \"home_input_high\": %s}",
		                 n ? ", " : "", (long long)axis->steps, angle, axis->steps_per_rev, axis->start_deg,
		                 motion_enabled(axis) ? "true" : "false", axis->dir_level ? "true" : "false",
		                 (unsigned long long)axis->pulses, (unsigned long long)axis->pulses_while_released,
		                 axis->logged, high, low, setup, hold, interval, released, axis->switch_wired ? "true" : "false",
		                 home ? "true" : "false");
	}
	if (used < size)
		snprintf(out + used, size - used, "]}");
}
