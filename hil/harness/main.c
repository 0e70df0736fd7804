/*
 * phantom-hil: run the real firmware image in simavr against the pneumatic plant.
 *
 * The plant is stepped at a fixed step in simulated time; ADC channels 0..2 read its sensors, the PWM
 * timers drive its blowers, USART0 is a pseudo-terminal. Line commands on stdin control it, and each
 * gets one JSON line on stdout (see hil/README.md). Time is paced to the wall clock times --speed.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <math.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "board.h"
#include "motion.h"
#include "plant.h"
#include "profile.h"
#include "serial_pty.h"
#include "avr_extint.h"
#include "sim_avr.h"
#include "sim_elf.h"

/* The notable stalls and host gaps kept (the last ones), and what makes one notable (s). */
#define NOTABLE_KEPT 8
#define NOTABLE_LAG_S 0.05
#define NOTABLE_GAP_S 0.25

typedef struct harness {
	avr_t *avr;                   /* NULL when running the plant alone (--no-mcu) */
	plant_t plant;
	serial_pty_t serial;
	profile_t profile;
	motion_t motion;              /* the stepper drivers' pins */
	int powered;                  /* the board has power (USB plugged in) and a running core */
	int halted;                   /* the core stopped by itself (crash or sleep with interrupts off) */
	double speed;                 /* 1 = wall clock, > 1 faster, 0 = as fast as possible */
	uint64_t frequency_hz;
	uint64_t cycle;               /* running cycle count: survives MCU resets, advances while unpowered */
	uint64_t last_core_cycle;
	uint64_t plant_step_cycles, service_cycles, byte_cycles;
	uint64_t next_plant_cycle, next_service_cycle, next_byte_cycle;
	double pace_origin_wall_s;
	uint64_t pace_origin_cycle;
	double max_lag_s;             /* the longest stall behind the clock */
	double lost_s;                /* wall-clock time the simulation could not keep up with, in total */
	/* the last NOTABLE_KEPT stalls of the harness behind the clock (over NOTABLE_LAG_S), and the last gaps in
	   the host's bytes to the UART (over NOTABLE_GAP_S of board time): what a DEAD_HOST on a loaded machine is
	   explained by (the harness starved, or the host silent while the board ran) */
	struct { double at_epoch_s, at_s, lag_s; } lags[NOTABLE_KEPT];
	struct { double at_epoch_s, at_s, gap_s, lost_s; size_t queued; } gaps[NOTABLE_KEPT];
	uint64_t lag_count, gap_count;
	double lost_at_host_byte_s;   /* lost_s when the UART last received a host byte */
	uint64_t resets;
	uint64_t last_reset_cycle;
	uint64_t steps;               /* simulator steps since `stats reset`: instructions, or jumps to the next event
	                                 while the core sleeps (the harness's work, whatever the wall clock does) */
	double all_off_since_s;       /* since when every commanded drive level is 0; < 0 while one is on */
	double last_host_byte_s;      /* when the UART last received a byte from the host; < 0 before any */
	uint32_t control_entry;       /* byte address of the control tick (the control_tick profile region), 0 if none */
	double reset_s;               /* when the core last started from its reset vector */
	double control_since_s;       /* when the control tick first ran after that; < 0 before */
	double floating_s;            /* time a blower pin spent floating between that reset and the control tick */
	int driven_before_control;    /* a blower pin was driven high or connected to PWM before the control tick */
	int bootloader;               /* a bootloader was loaded: the reset vector is its start */
	double peak_pa[3];            /* each chamber's highest true pressure since the last `fault` command */
	double nominal_supply_v;      /* the 5 V rail as the plant file gives it */
	int rt_priority;              /* --rt-priority: the SCHED_FIFO priority asked for while paced (0: none) */
	int realtime;                 /* running at it now */
	char scheduling[256];         /* what the harness runs at, and why (for `state`) */
	double busy_window_start_s;   /* the start of the wall-clock window measured for the real-time guard */
	double busy_window_slept_s;   /* how long the harness slept in it */
	char line[1024];
	size_t line_length;
	int quit;
} harness_t;

/* The time of day (s since the epoch): when a notable stall or gap happened, to set beside a host's log. */
static double epoch_seconds(void)
{
	struct timespec now;
	clock_gettime(CLOCK_REALTIME, &now);
	return now.tv_sec + now.tv_nsec * 1e-9;
}

/* Monotonic wall-clock time in seconds. */
static double wall_seconds(void)
{
	struct timespec now;
	clock_gettime(CLOCK_MONOTONIC, &now);
	return now.tv_sec + now.tv_nsec * 1e-9;
}

/* Simulated time since start (s), from the running cycle count. */
static double simulated_seconds(const harness_t *h)
{
	return (double)h->cycle / (double)h->frequency_hz;
}

/* Print one JSON reply line. */
static void reply(const char *format, ...) __attribute__((format(printf, 1, 2)));
static void reply(const char *format, ...)
{
	va_list args;
	va_start(args, format);
	vprintf(format, args);
	va_end(args);
	putchar('\n');
	fflush(stdout);
}

/* Print a JSON array of three numbers. */
static void format_triple(char *out, size_t size, const double values[3], double scale)
{
	snprintf(out, size, "[%.9g, %.9g, %.9g]", values[0] * scale, values[1] * scale, values[2] * scale);
}

/* Answer `state`: the plant and the board as the bench sees them. */
static void reply_state(harness_t *h)
{
	double volumes_m3[3], voltages_v[3], effective[3];
	char pressures[96], drives[96], volumes[96], sensed[96], actual[96];
	plant_chamber_volumes(&h->plant, volumes_m3);
	for (int i = 0; i < 3; i++) {
		voltages_v[i] = h->plant.sensor_cut[i] ? 0.0 : h->plant.params.sensor_supply_v
		                  * (h->plant.params.sensor_gain_per_pa * (h->plant.sensed_pressure_pa[i]
		                  + h->plant.params.sensor_offset_pa[i]) + 0.5);
		effective[i] = plant_effective_drive(&h->plant, i);
	}
	format_triple(pressures, sizeof(pressures), h->plant.pressure_pa, 1.0);
	format_triple(drives, sizeof(drives), h->plant.drive_level, 1.0);
	format_triple(actual, sizeof(actual), effective, 1.0);
	format_triple(volumes, sizeof(volumes), volumes_m3, 1e6);
	format_triple(sensed, sizeof(sensed), voltages_v, 1.0);
	char off_since[32] = "null", last_byte[32] = "null";
	if (h->all_off_since_s >= 0)
		snprintf(off_since, sizeof(off_since), "%.9f", h->all_off_since_s);
	if (h->last_host_byte_s >= 0)
		snprintf(last_byte, sizeof(last_byte), "%.9f", h->last_host_byte_s);
	char pins[96] = "null", control_since[32] = "null", peaks[96], motion[256] = "null";
	format_triple(peaks, sizeof(peaks), h->peak_pa, 1.0);
	if (h->avr) {
		motion_format_positions(&h->motion, motion, sizeof(motion));
		pin_mode_t modes[3];
		board_blower_pin_modes(h->avr, modes);
		snprintf(pins, sizeof(pins), "[\"%s\", \"%s\", \"%s\"]", pin_mode_names[modes[0]], pin_mode_names[modes[1]],
		         pin_mode_names[modes[2]]);
	}
	if (h->control_since_s >= 0)
		snprintf(control_since, sizeof(control_since), "%.9f", h->control_since_s);
	char lags[NOTABLE_KEPT * 64 + 8] = "[", gaps[NOTABLE_KEPT * 96 + 8] = "[";
	size_t lags_used = 1, gaps_used = 1;
	uint64_t first = h->lag_count > NOTABLE_KEPT ? h->lag_count - NOTABLE_KEPT : 0;
	for (uint64_t k = first; k < h->lag_count; k++) {
		const typeof(h->lags[0]) *lag = &h->lags[k % NOTABLE_KEPT];
		lags_used += snprintf(lags + lags_used, sizeof(lags) - lags_used, "%s[%.3f, %.3f, %.3f]", k > first ? ", " : "",
		                      lag->at_epoch_s, lag->at_s, lag->lag_s);
	}
	snprintf(lags + lags_used, sizeof(lags) - lags_used, "]");
	first = h->gap_count > NOTABLE_KEPT ? h->gap_count - NOTABLE_KEPT : 0;
	for (uint64_t k = first; k < h->gap_count; k++) {
		const typeof(h->gaps[0]) *gap = &h->gaps[k % NOTABLE_KEPT];
		gaps_used += snprintf(gaps + gaps_used, sizeof(gaps) - gaps_used, "%s[%.3f, %.3f, %.3f, %.3f, %zu]",
		                      k > first ? ", " : "", gap->at_epoch_s, gap->at_s, gap->gap_s, gap->lost_s, gap->queued);
	}
	snprintf(gaps + gaps_used, sizeof(gaps) - gaps_used, "]");
	struct timespec cpu;
	clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cpu);
	reply("{\"time_s\": %.9f, \"all_off_since_s\": %s, \"last_host_byte_s\": %s, \"pressures_pa\": %s, \"drive_levels\": %s, \"effective_drive_levels\": %s, "
	      "\"chamber_volumes_ml\": %s, \"sensor_voltages_v\": %s, \"powered\": %s, \"halted\": %s, "
	      "\"resets\": %llu, \"max_lag_s\": %.6f, \"lost_s\": %.6f, \"blower_pins\": %s, \"reset_s\": %.9f, "
	      "\"control_since_s\": %s, \"floating_before_control_s\": %.6f, \"driven_before_control\": %s, "
	      "\"peak_pressures_pa\": %s, \"motion\": %s, \"lags\": %s, \"host_gaps\": %s, \"scheduling\": \"%s\", "
	      "\"cpu_s\": %.3f}",
	      simulated_seconds(h), off_since, last_byte, pressures, drives, actual, volumes, sensed, h->powered ? "true" : "false",
	      h->halted ? "true" : "false", (unsigned long long)h->resets, h->max_lag_s, h->lost_s, pins, h->reset_s,
	      control_since, h->floating_s, h->driven_before_control ? "true" : "false", peaks, motion, lags, gaps,
	      h->scheduling, cpu.tv_sec + cpu.tv_nsec * 1e-9);
}

/* Answer `stats`: cycle counts of the timed functions and the serial line counters. */
static void reply_stats(harness_t *h)
{
	char regions[2048] = "";
	size_t used = 0;
	for (int k = 0; k < h->profile.count; k++) {
		profile_region_t *r = &h->profile.regions[k];
		used += snprintf(regions + used, sizeof(regions) - used,
		                 "%s\"%s\": {\"calls\": %llu, \"short_calls\": %llu, \"total_cycles\": %llu, "
		                 "\"max_cycles\": %llu}",
		                 k ? ", " : "", r->name, (unsigned long long)r->calls, (unsigned long long)r->short_calls,
		                 (unsigned long long)r->total_cycles, (unsigned long long)r->max_cycles);
	}
	serial_pty_t *s = &h->serial;
	char stack[24] = "null";
	if (h->avr && h->profile.min_sp != 0xFFFF)
		snprintf(stack, sizeof(stack), "%d", (int)h->avr->ramend - (int)h->profile.min_sp);
	reply("{\"elapsed_cycles\": %llu, \"busy_cycles\": %llu, \"simulator_steps\": %llu, \"frequency_hz\": %llu, \"stack_bytes_max\": %s, \"regions\": {%s}, \"serial\": {\"bytes_to_mcu\": %llu, "
	      "\"bytes_from_mcu\": %llu, \"bytes_dropped\": %llu, \"bytes_flipped\": %llu, \"bytes_overflowed\": %llu, \"frames_dropped\": %llu}}",
	      (unsigned long long)(h->cycle - h->profile.since_cycle), (unsigned long long)h->profile.busy_cycles,
	      (unsigned long long)h->steps, (unsigned long long)h->frequency_hz, stack, regions,
	      (unsigned long long)s->bytes_to_mcu, (unsigned long long)s->bytes_from_mcu,
	      (unsigned long long)s->bytes_dropped, (unsigned long long)s->bytes_flipped,
	      (unsigned long long)s->bytes_overflowed, (unsigned long long)s->frames_dropped);
}

/* Advance the plant one fixed step with the drive levels the firmware commands now. */
static void step_plant(harness_t *h)
{
	if (h->avr && h->powered && !h->halted)
		board_read_drive_levels(h->avr, h->plant.drive_level);
	else if (h->avr)
		h->plant.drive_level[0] = h->plant.drive_level[1] = h->plant.drive_level[2] = 0.0;
	plant_step(&h->plant, h->plant.params.step_s);
	if (h->avr && h->powered && !h->halted && h->control_since_s < 0) {
		pin_mode_t modes[3];
		board_blower_pin_modes(h->avr, modes);
		int floating = 0;
		for (int i = 0; i < 3; i++) {
			floating |= modes[i] == PIN_FLOATING || modes[i] == PIN_PULLUP;
			h->driven_before_control |= modes[i] == PIN_HIGH || modes[i] == PIN_PWM;
		}
		if (floating)
			h->floating_s += h->plant.params.step_s;
	}
	for (int i = 0; i < 3; i++)
		if (h->plant.pressure_pa[i] > h->peak_pa[i])
			h->peak_pa[i] = h->plant.pressure_pa[i];
	if (h->avr)
		motion_step(&h->motion, simulated_seconds(h));
	int any_on = h->plant.drive_level[0] > 0 || h->plant.drive_level[1] > 0 || h->plant.drive_level[2] > 0;
	if (any_on)
		h->all_off_since_s = -1;
	else if (h->all_off_since_s < 0)
		h->all_off_since_s = simulated_seconds(h);
}

/* Parse a chamber index argument; -1 if invalid. */
static int parse_chamber(const char *text)
{
	if (!text || text[1] || text[0] < '0' || text[0] > '2')
		return -1;
	return text[0] - '0';
}

/* Parse a number argument into *value; 0 on success. */
static int parse_number(const char *text, double *value)
{
	char *end;
	if (!text)
		return -1;
	*value = strtod(text, &end);
	return (end == text || *end || !isfinite(*value)) ? -1 : 0;
}

/* Run a `fault ...` command: inject into the plant or the line, or clear. */
static void handle_fault(harness_t *h, char **words, int count)
{
	double value = 0, other = 0;
	int chamber = count > 2 ? parse_chamber(words[2]) : -1;
	for (int i = 0; i < 3; i++)
		h->peak_pa[i] = h->plant.pressure_pa[i];
	const char *kind = words[1];
	if (!strcmp(kind, "clear") && h->avr) {
		uint32_t nominal_mv = (uint32_t)lround(h->nominal_supply_v * 1000.0);
		h->avr->vcc = h->avr->avcc = h->avr->aref = nominal_mv;
		h->plant.params.sensor_supply_v = h->nominal_supply_v;
	}
	if (!strcmp(kind, "clear")) {
		for (int i = 0; i < 3; i++) {
			h->plant.sensor_cut[i] = 0;
			h->plant.tube_off[i] = 0;
			h->plant.fault_leak_m3_per_s_per_pa[i] = 0;
			h->plant.stuck_drive_level[i] = -1;
		}
		h->serial.flip_probability = h->serial.drop_probability = 0;
		h->serial.drop_frames_left = 0;
	} else if (!strcmp(kind, "sensor_cut") && count == 3 && chamber >= 0) {
		h->plant.sensor_cut[chamber] = 1;
	} else if (!strcmp(kind, "supply") && count == 3 && h->avr && !parse_number(words[2], &value) && value >= 2.0
	           && value <= 5.5) {
		/* the board's 5 V rail sags: AVcc (the ADC's reference) and the sensors' supply with it */
		h->avr->vcc = h->avr->avcc = h->avr->aref = (uint32_t)lround(value * 1000.0);
		h->plant.params.sensor_supply_v = value;
	} else if (!strcmp(kind, "tube_off") && count == 3 && chamber >= 0) {
		h->plant.tube_off[chamber] = 1;
	} else if (!strcmp(kind, "leak") && count == 4 && chamber >= 0 && !parse_number(words[3], &value) && value >= 0) {
		h->plant.fault_leak_m3_per_s_per_pa[chamber] = value;
	} else if (!strcmp(kind, "stuck_blower") && count == 4 && chamber >= 0 && !parse_number(words[3], &value)
	           && value >= 0 && value <= 1) {
		h->plant.stuck_drive_level[chamber] = value;
	} else if (!strcmp(kind, "line_noise") && count == 4 && !parse_number(words[2], &value)
	           && !parse_number(words[3], &other) && value >= 0 && value <= 1 && other >= 0 && other <= 1) {
		h->serial.flip_probability = value;
		h->serial.drop_probability = other;
	} else if (!strcmp(kind, "drop_frame") && count == 4 && !parse_number(words[2], &value) && value >= 1
	           && value <= 255 && value == floor(value) && !parse_number(words[3], &other) && other >= 1
	           && other <= 1000 && other == floor(other)) {
		/* the next OTHER frames from the board with message id VALUE are lost whole */
		h->serial.drop_msg_id = (int)value;
		h->serial.drop_frames_left = (uint32_t)other;
	} else {
		reply("{\"error\": \"bad fault command: use 'fault sensor_cut CH', 'fault tube_off CH', 'fault supply VOLTS', 'fault leak CH M3_PER_S_PER_PA', "
		      "'fault stuck_blower CH LEVEL', 'fault line_noise FLIP_PROB DROP_PROB', 'fault drop_frame MSG_ID COUNT' or 'fault clear'\"}");
		return;
	}
	reply("{\"ok\": true, \"time_s\": %.9f}", simulated_seconds(h));
}

/* Parse an axis index argument; -1 if invalid. */
static int parse_axis(const char *text)
{
	if (!text || text[1] || text[0] < '0' || text[0] >= '0' + MOTION_AXES)
		return -1;
	return text[0] - '0';
}

/* Run a `motion ...` command: report the stepper axes, set the simulated mechanism or home switch, write a pulse
   log, or reset the counters. */
static void handle_motion(harness_t *h, char **words, int count)
{
	double steps_per_rev = 0, start_deg = 0, low = 0, high = 0, level = 0;
	int axis = count > 2 ? parse_axis(words[2]) : -1;
	const char *what = count > 1 ? words[1] : "";
	if (count == 1) {
		char details[2048];
		motion_format_details(&h->motion, details, sizeof(details));
		reply("%s", details);
		return;
	}
	if (!strcmp(what, "reset") && count == 2) {
		motion_reset_counters(&h->motion);
	} else if (!strcmp(what, "axis") && count == 5 && axis >= 0 && !parse_number(words[3], &steps_per_rev)
	           && steps_per_rev >= 0 && !parse_number(words[4], &start_deg)) {
		h->motion.axes[axis].steps_per_rev = steps_per_rev;
		h->motion.axes[axis].start_deg = start_deg;
	} else if (!strcmp(what, "switch") && count == 4 && axis >= 0 && !strcmp(words[3], "off")) {
		motion_set_switch(&h->motion.axes[axis], 0, 0, 0, 1);
	} else if (!strcmp(what, "switch") && count == 6 && axis >= 0 && !parse_number(words[3], &low)
	           && !parse_number(words[4], &high) && low <= high && !parse_number(words[5], &level)
	           && (level == 0 || level == 1)) {
		motion_set_switch(&h->motion.axes[axis], 1, low, high, (int)level);
	} else if (!strcmp(what, "log") && count == 4 && axis >= 0) {
		long written = motion_write_log(&h->motion.axes[axis], words[3]);
		if (written < 0)
			reply("{\"error\": \"cannot write the pulse log to %s: %s\"}", words[3], strerror(errno));
		else
			reply("{\"ok\": true, \"count\": %ld}", written);
		return;
	} else {
		reply("{\"error\": \"bad motion command: use 'motion', 'motion reset', 'motion axis AXIS STEPS_PER_REV "
		      "START_DEG', 'motion switch AXIS LOW_DEG HIGH_DEG ACTIVE_LEVEL', 'motion switch AXIS off' or "
		      "'motion log AXIS PATH'\"}");
		return;
	}
	reply("{\"ok\": true, \"time_s\": %.9f}", simulated_seconds(h));
}

/* Data-space address of MCUSR (the reset cause), the same on the ATmega328P and the ATmega2560. */
#define MCUSR_ADDRESS 0x54
#define MCUSR_POWER_ON 0x01
#define MCUSR_EXTERNAL 0x02

/* A new start from the reset vector (the bootloader's, if one is loaded): watch the blower pins until the
   control tick runs. */
static void note_reset(harness_t *h)
{
	h->reset_s = simulated_seconds(h);
	h->control_since_s = -1;
	h->floating_s = 0;
	h->driven_before_control = 0;
}

/* simavr polls a low-level external interrupt pin on every cycle while it reads low, whether or not the interrupt
   is enabled ("strict level triggering", avr_extint.c; on by default and again after every reset). The firmware
   enables no external interrupt, and its STEP0 and blower-2 outputs sit on the Uno's INT0 and INT1 pins (PD2,
   PD3) and stay low for minutes: that polling, one simulator callback per cycle, took most of the harness's CPU
   (an idle Uno ran at 0.87x the wall clock flat out, no faster than asked for 1x). Without it a low level raises
   the interrupt flag once, as a falling edge does; with EIMSK clear the core sees neither. Called at each reset,
   before the core runs its first instruction, so no poll is started. */
static void no_level_polling(avr_t *avr)
{
	for (uint8_t n = 0; n < EXTINT_COUNT; n++)
		avr_extint_set_strict_lvl_trig(avr, n, 0);
}

/* Start the core with a reset flag in MCUSR: power-on as a board gets power, external as a DTR pulse does
   (through the USB-serial chip's capacitor into RESET). */
static void power_on_with(harness_t *h, uint8_t mcusr_flag)
{
	avr_reset(h->avr);
	no_level_polling(h->avr);
	h->avr->data[MCUSR_ADDRESS] |= mcusr_flag;
	note_reset(h);
	h->last_core_cycle = h->avr->cycle;
	h->powered = 1;
	h->halted = 0;
	profile_reset(&h->profile, h->cycle);
}

static void power_on(harness_t *h) { power_on_with(h, MCUSR_POWER_ON); }

/* Load an Intel HEX image into flash (data, end of file, extended segment and linear address records; start
   address records are ignored: a bootloader runs from the reset vector). The lowest address loaded goes to
   *start. NULL on success, else what was wrong. (simavr's reader refuses the start segment record that
   avr-objcopy writes into Optiboot's .hex.) */
static const char *load_intel_hex(const char *path, uint8_t *flash, uint32_t flash_size, uint32_t *start)
{
	FILE *file = fopen(path, "r");
	if (!file)
		return strerror(errno);
	char line[600];
	uint32_t base = 0, lowest = UINT32_MAX;
	const char *problem = "no end-of-file record";
	while (fgets(line, sizeof(line), file)) {
		unsigned count, address, type, byte, sum = 0;
		if (line[0] != ':' || sscanf(line + 1, "%2x%4x%2x", &count, &address, &type) != 3) {
			problem = "a line is not an Intel HEX record";
			break;
		}
		uint8_t data[256];
		for (unsigned k = 0; k <= count; k++) {
			if (sscanf(line + 9 + 2 * k, "%2x", &byte) != 1)
				break;
			if (k < count)
				data[k] = (uint8_t)byte;
			sum += byte;
		}
		sum += count + (address >> 8) + (address & 0xFF) + type;
		if (sum & 0xFF) {
			problem = "a record's checksum is wrong";
			break;
		}
		if (type == 1) {
			problem = NULL;
			break;
		}
		if (type == 2 || type == 4) {
			base = ((uint32_t)data[0] << 8 | data[1]) << (type == 2 ? 4 : 16);
		} else if (type == 0) {
			uint32_t at = base + address;
			if (at + count > flash_size) {
				problem = "it does not fit this MCU's flash";
				break;
			}
			memcpy(flash + at, data, count);
			if (at < lowest)
				lowest = at;
		}
	}
	fclose(file);
	if (!problem && lowest == UINT32_MAX)
		problem = "it holds no data";
	*start = lowest;
	return problem;
}

/* Run one stdin command. */
static void handle_command(harness_t *h, char *line)
{
	char *words[8];
	int count = 0;
	for (char *word = strtok(line, " \t\r\n"); word && count < 8; word = strtok(NULL, " \t\r\n"))
		words[count++] = word;
	if (count == 0)
		return;
	const char *command = words[0];
	double value;
	if (!strcmp(command, "state")) {
		reply_state(h);
	} else if (!strcmp(command, "stats")) {
		reply_stats(h);
		if (count > 1 && !strcmp(words[1], "reset")) {
			profile_reset(&h->profile, h->cycle);
			h->steps = 0;
		}
	} else if (!strcmp(command, "fault") && count >= 2) {
		handle_fault(h, words, count);
	} else if (!strcmp(command, "motion") && h->avr) {
		handle_motion(h, words, count);
	} else if (!strcmp(command, "unplug") && h->avr) {
		if (h->powered)
			serial_pty_close(&h->serial);
		h->powered = 0;
		reply("{\"ok\": true}");
	} else if (!strcmp(command, "replug") && h->avr) {
		if (!h->powered) {
			if (serial_pty_open(&h->serial) < 0) {
				reply("{\"error\": \"cannot create the pty: %s\"}", strerror(errno));
				return;
			}
			power_on(h);
		}
		reply("{\"ok\": true, \"pty\": \"%s\"}", h->serial.slave_path);
	} else if (!strcmp(command, "reset") && h->avr && count <= 2) {
		if (count == 2 && !strcmp(words[1], "external"))
			power_on_with(h, MCUSR_EXTERNAL);
		else if (count == 1 || !strcmp(words[1], "power"))
			power_on(h);
		else {
			reply("{\"error\": \"reset takes 'power' (the default) or 'external'\"}");
			return;
		}
		reply("{\"ok\": true, \"time_s\": %.9f}", simulated_seconds(h));
	} else if (!strcmp(command, "drive") && !h->avr && count == 4) {
		for (int i = 0; i < 3; i++)
			if (parse_number(words[i + 1], &h->plant.drive_level[i])) {
				reply("{\"error\": \"drive takes three numbers\"}");
				return;
			}
		reply("{\"ok\": true}");
	} else if (!strcmp(command, "advance") && !h->avr && count == 2 && !parse_number(words[1], &value) && value >= 0) {
		uint64_t target = h->cycle + (uint64_t)llround(value * h->frequency_hz);
		while (h->cycle + h->plant_step_cycles <= target) {
			h->cycle += h->plant_step_cycles;
			step_plant(h);
		}
		reply_state(h);
	} else if (!strcmp(command, "quit")) {
		h->quit = 1;
		reply("{\"ok\": true}");
	} else {
		reply("{\"error\": \"unknown command '%s': use state, stats [reset], fault ..., motion ..., unplug, replug, reset, quit%s\"}",
		      command, h->avr ? "" : ", drive U0 U1 U2, advance SECONDS");
	}
}

/* Read what is available on stdin and run each complete line; EOF quits. */
static void poll_commands(harness_t *h, int timeout_ms)
{
	struct pollfd fd = {.fd = STDIN_FILENO, .events = POLLIN};
	if (poll(&fd, 1, timeout_ms) <= 0)
		return;
	char buffer[512];
	ssize_t got = read(STDIN_FILENO, buffer, sizeof(buffer));
	if (got <= 0) {
		h->quit = 1;
		return;
	}
	for (ssize_t k = 0; k < got; k++) {
		if (buffer[k] == '\n') {
			h->line[h->line_length] = 0;
			handle_command(h, h->line);
			h->line_length = 0;
		} else if (h->line_length + 1 < sizeof(h->line)) {
			h->line[h->line_length++] = buffer[k];
		}
	}
}

/* How far simulated time may fall behind the clock before the difference is given up (s). */
#define PACE_SLACK_S 0.01
/* How far simulated time may run ahead of the clock before the harness sleeps (s): a sleep every millisecond of
   board time (the service period) cost a third of a paced board's CPU. */
#define PACE_AHEAD_S 0.002

/* The real-time guard: a harness at a real-time priority that slept less than REALTIME_MIN_SLEEP of a window of
   REALTIME_WINDOW_S cannot keep up at its speed on this machine (flat out it runs about 7x real time); it gives
   the priority up, for good, rather than take a core from every other process. Paced at 2x it sleeps 60-80 % of
   each window. The window is short because until it ends the harness holds a core from every normal process: a
   window of a second held one for a second from the simavr tests beside a flat-out harness (make test's [sim]
   run, whose host links run at normal priority). */
#define REALTIME_MIN_SLEEP 0.1
#define REALTIME_WINDOW_S 0.2

/* Ask for SCHED_FIFO at --rt-priority (a paced board only: unpaced, it runs flat out). The simulated board
   stands in for hardware, which never waits for a core: a harness that waited a second for one (a loaded
   machine) sent the host nothing for that second, and the host, taking the board for gone, reconnected and let
   its dead-host deadline pass. Below the board link's priority (phantom.host.link_process), so that the host's
   keepalive never waits for the simulator. Refused (no CAP_SYS_NICE, no RLIMIT_RTPRIO): normal, and says why. */
static void ask_realtime(harness_t *h)
{
	if (h->rt_priority <= 0) {
		snprintf(h->scheduling, sizeof(h->scheduling), "normal (no real-time priority asked)");
		return;
	}
	if (h->speed <= 0) {
		snprintf(h->scheduling, sizeof(h->scheduling), "normal (unpaced: never a real-time priority)");
		return;
	}
	struct sched_param param = {.sched_priority = h->rt_priority};
	if (sched_setscheduler(0, SCHED_FIFO | SCHED_RESET_ON_FORK, &param) < 0) {
		snprintf(h->scheduling, sizeof(h->scheduling), "normal (SCHED_FIFO %d refused: %s)", h->rt_priority,
		         strerror(errno));
		return;
	}
	h->realtime = 1;
	snprintf(h->scheduling, sizeof(h->scheduling), "SCHED_FIFO %d", h->rt_priority);
}

/* The real-time guard (REALTIME_MIN_SLEEP), checked once a window of REALTIME_WINDOW_S of wall clock. */
static void guard_realtime(harness_t *h, double now_s)
{
	double window_s = now_s - h->busy_window_start_s;
	if (window_s < REALTIME_WINDOW_S)
		return;
	double slept = h->busy_window_slept_s / window_s;
	h->busy_window_start_s = now_s;
	h->busy_window_slept_s = 0;
	if (!h->realtime || slept >= REALTIME_MIN_SLEEP)
		return;
	struct sched_param param = {.sched_priority = 0};
	if (sched_setscheduler(0, SCHED_OTHER, &param) < 0)
		return;
	h->realtime = 0;
	snprintf(h->scheduling, sizeof(h->scheduling), "normal (SCHED_FIFO %d given up at board time %.3f s: it slept "
	         "%.0f %% of %.1f s, it cannot keep up at speed %g)", h->rt_priority, simulated_seconds(h),
	         100 * slept, window_s, h->speed);
	fprintf(stderr, "phantom-hil: %s\n", h->scheduling);
}

/* Sleep until the wall clock catches up with simulated time divided by the speed, once simulated time is
   PACE_AHEAD_S ahead; bytes from the host or a command end the sleep early, so they wait no longer than before. */
static void pace(harness_t *h)
{
	if (h->speed <= 0)
		return;
	double target_s = h->pace_origin_wall_s + (double)(h->cycle - h->pace_origin_cycle) / h->frequency_hz / h->speed;
	double now_s = wall_seconds();
	double ahead_s = target_s - now_s;
	guard_realtime(h, now_s);
	if (ahead_s >= PACE_AHEAD_S) {
		struct timespec pause = {.tv_sec = (time_t)ahead_s, .tv_nsec = (long)((ahead_s - floor(ahead_s)) * 1e9)};
		struct pollfd input[2] = {
			{.fd = serial_pty_wants_input(&h->serial) ? h->serial.master_fd : -1, .events = POLLIN},
			{.fd = STDIN_FILENO, .events = POLLIN}};
		ppoll(input, 2, &pause, NULL);
		h->busy_window_slept_s += wall_seconds() - now_s;
	} else if (-ahead_s > PACE_SLACK_S) {
		/* behind the clock: give the time up rather than catch it up later, so that simulated time never runs
		   faster than asked (a host deadline never shrinks by more than PACE_AHEAD_S) */
		if (-ahead_s > h->max_lag_s)
			h->max_lag_s = -ahead_s;
		h->lost_s += -ahead_s;
		if (-ahead_s > NOTABLE_LAG_S) {
			typeof(h->lags[0]) *lag = &h->lags[h->lag_count++ % NOTABLE_KEPT];
			lag->at_epoch_s = epoch_seconds();
			lag->at_s = simulated_seconds(h);
			lag->lag_s = -ahead_s;
		}
		h->pace_origin_wall_s = now_s;
		h->pace_origin_cycle = h->cycle;
	}
}

/* Periodic housekeeping: the pty, the pacing, the commands. The pacing first: a lag that the harness gives up
   (a stall of its process) is then in the lost_s that the next command reports, not in the one after it, which
   counted it in the wrong window (test_simulated_time_is_paced_to_the_wall_clock: 0.068 s of board time too many
   on a loaded machine). */
static void service(harness_t *h)
{
	serial_pty_poll(&h->serial);
	pace(h);
	poll_commands(h, 0);
}

/* Keep simavr from sleeping in real time when the firmware sleeps: pacing is ours. */
static void no_sleep(avr_t *avr, avr_cycle_count_t how_long)
{
	(void)avr;
	(void)how_long;
}

/* Run one instruction (or one step of an unpowered board) and the due periodic work. */
static void run_once(harness_t *h)
{
	if (h->powered && !h->halted) {
		int state = avr_run(h->avr);
		h->steps++;
		uint64_t core_cycle = h->avr->cycle;
		h->cycle += core_cycle - h->last_core_cycle;
		h->last_core_cycle = core_cycle;
		if (h->avr->pc == h->avr->reset_pc && state != cpu_Sleeping && h->cycle - h->last_reset_cycle > 4) {
			/* the core restarted (watchdog): a function being timed never returns */
			no_level_polling(h->avr);
			h->resets++;
			h->last_reset_cycle = h->cycle;
			profile_abort(&h->profile);
			if (h->control_since_s >= 0)
				note_reset(h);  /* a reset inside a bootloader's wait belongs to the start being watched */
		} else if (h->bootloader && h->avr->pc == 0) {
			profile_abort(&h->profile);  /* the bootloader starts the application */
		}
		if (h->control_since_s < 0 && h->control_entry && h->avr->pc == h->control_entry)
			h->control_since_s = simulated_seconds(h);
		if (h->profile.count)
			profile_check(&h->profile, h->avr, h->cycle);
		if (state == cpu_Done || state == cpu_Crashed) {
			fprintf(stderr, "phantom-hil: the core stopped (state %d) at pc 0x%x\n", state, h->avr->pc);
			h->halted = 1;
		}
	} else {
		h->cycle = h->next_plant_cycle < h->next_service_cycle ? h->next_plant_cycle : h->next_service_cycle;
	}
	while (h->cycle >= h->next_byte_cycle) {
		if (h->powered && !h->halted && serial_pty_feed(&h->serial)) {
			double now_s = simulated_seconds(h);
			if (h->last_host_byte_s >= 0 && now_s - h->last_host_byte_s > NOTABLE_GAP_S) {
				typeof(h->gaps[0]) *gap = &h->gaps[h->gap_count++ % NOTABLE_KEPT];
				gap->at_epoch_s = epoch_seconds();
				gap->at_s = now_s;
				gap->gap_s = now_s - h->last_host_byte_s;
				gap->lost_s = h->lost_s - h->lost_at_host_byte_s;
				gap->queued = h->serial.to_mcu_count;
			}
			h->last_host_byte_s = now_s;
			h->lost_at_host_byte_s = h->lost_s;
		}
		h->next_byte_cycle += h->byte_cycles;
	}
	while (h->cycle >= h->next_plant_cycle) {
		step_plant(h);
		h->next_plant_cycle += h->plant_step_cycles;
	}
	if (h->cycle >= h->next_service_cycle) {
		service(h);
		h->next_service_cycle += h->service_cycles;
	}
}

/* Print what was wrong and the usage, and exit with status 2. */
static void usage(const char *message)
{
	fprintf(stderr, "phantom-hil: %s\n"
	        "usage: phantom-hil (--elf FIRMWARE.elf [--mcu atmega328p] [--link PATH] [--baud 115200]\n"
	        "                    [--speed 1.0] [--rt-priority 0] [--profile NAME=0xADDR[:MIN_CYCLES]]...\n"
	        "                    [--bootloader FILE.hex]\n"
	        "                    | --no-mcu)\n"
	        "                   [--frequency 16000000] [--seed 0] --param NAME=VALUE...\n", message);
	exit(2);
}

/* Parse the options, load the image, wire it to the plant and the pty, and run until `quit` or EOF. */
int main(int argc, char **argv)
{
	static harness_t harness;
	harness_t *h = &harness;
	const char *elf_path = NULL, *mcu = "atmega328p", *bootloader_path = NULL;
	int no_mcu = 0;
	unsigned long long seed = 0;
	double baud = 115200;
	plant_params_t params;
	plant_unset_params(&params);
	h->speed = 1.0;
	h->frequency_hz = 16000000;
	h->serial.master_fd = h->serial.slave_fd = -1;
	h->serial.drop_msg_id = h->serial.held_code = -1;
	static const struct option options[] = {
		{"elf", required_argument, 0, 'e'}, {"mcu", required_argument, 0, 'm'},
		{"link", required_argument, 0, 'l'}, {"baud", required_argument, 0, 'b'},
		{"speed", required_argument, 0, 's'}, {"profile", required_argument, 0, 'p'},
		{"no-mcu", no_argument, 0, 'n'}, {"frequency", required_argument, 0, 'f'},
		{"seed", required_argument, 0, 'r'}, {"param", required_argument, 0, 'k'},
		{"bootloader", required_argument, 0, 'B'}, {"rt-priority", required_argument, 0, 'R'}, {0, 0, 0, 0},
	};
	int option;
	while ((option = getopt_long(argc, argv, "", options, NULL)) != -1) {
		char *equals;
		double value;
		switch (option) {
		case 'e': elf_path = optarg; break;
		case 'm': mcu = optarg; break;
		case 'l': snprintf(h->serial.link_path, sizeof(h->serial.link_path), "%s", optarg); break;
		case 'b': if (parse_number(optarg, &baud) || baud <= 0) usage("--baud takes a positive number"); break;
		case 's': if (parse_number(optarg, &h->speed) || h->speed < 0) usage("--speed takes a number >= 0"); break;
		case 'n': no_mcu = 1; break;
		case 'B': bootloader_path = optarg; break;
		case 'R':
			if (parse_number(optarg, &value) || value < 0 || value > 99 || value != floor(value))
				usage("--rt-priority takes a SCHED_FIFO priority, 1 to 99 (0: none)");
			h->rt_priority = (int)value;
			break;
		case 'f': h->frequency_hz = strtoull(optarg, NULL, 0); break;
		case 'r': seed = strtoull(optarg, NULL, 0); break;
		case 'p':
			if (profile_add(&h->profile, optarg)) usage("--profile takes NAME=0xADDRESS[:MIN_CYCLES] (at most 24)");
			break;
		case 'k':
			equals = strchr(optarg, '=');
			if (!equals) usage("--param takes NAME=VALUE");
			*equals = 0;
			if (parse_number(equals + 1, &value) || plant_set_param(&params, optarg, value)) {
				fprintf(stderr, "phantom-hil: unknown plant parameter or bad value: %s=%s\n", optarg, equals + 1);
				return 2;
			}
			break;
		default: usage("unknown option");
		}
	}
	if (!no_mcu && !elf_path)
		usage("give --elf FIRMWARE.elf, or --no-mcu to run the plant alone");
	if (h->frequency_hz == 0)
		usage("--frequency must be positive");
	const char *problem = plant_check_params(&params);
	if (problem) {
		fprintf(stderr, "phantom-hil: %s\n", problem);
		return 2;
	}
	plant_init(&h->plant, &params, seed);
	h->all_off_since_s = 0;
	h->last_host_byte_s = -1;
	h->plant_step_cycles = (uint64_t)llround(params.step_s * h->frequency_hz);
	if (h->plant_step_cycles == 0)
		h->plant_step_cycles = 1;
	h->service_cycles = h->frequency_hz / 1000;
	h->byte_cycles = (uint64_t)llround(10.0 * h->frequency_hz / baud);
	signal(SIGPIPE, SIG_IGN);

	if (no_mcu) {
		snprintf(h->scheduling, sizeof(h->scheduling), "normal (the plant alone: not paced)");
		reply("{\"ready\": true, \"mcu\": null}");
		while (!h->quit)
			poll_commands(h, -1);
		return 0;
	}

	static elf_firmware_t firmware;
	/* simavr prints loader chatter on stdout, which is our reply channel: send it to stderr */
	fflush(stdout);
	int saved_stdout = dup(STDOUT_FILENO);
	dup2(STDERR_FILENO, STDOUT_FILENO);
	int unreadable = elf_read_firmware(elf_path, &firmware);
	if (unreadable) {
		fprintf(stderr, "phantom-hil: cannot read the firmware image %s\n", elf_path);
		return 2;
	}
	h->avr = avr_make_mcu_by_name(mcu);
	if (!h->avr) {
		fprintf(stderr, "phantom-hil: simavr does not know the MCU '%s'\n", mcu);
		return 2;
	}
	avr_init(h->avr);
	h->avr->log = 0;
	h->avr->frequency = h->frequency_hz;
	h->avr->vcc = h->avr->avcc = h->avr->aref = (uint32_t)lround(params.sensor_supply_v * 1000.0);
	h->nominal_supply_v = params.sensor_supply_v;
	h->avr->sleep = no_sleep;
	avr_load_firmware(h->avr, &firmware);
	if (bootloader_path) {
		/* Flash the bootloader where its .hex puts it, and start from there (the BOOTRST fuse of an Arduino) */
		uint32_t start = 0;
		const char *problem = load_intel_hex(bootloader_path, h->avr->flash, h->avr->flashend + 1, &start);
		if (problem) {
			fprintf(stderr, "phantom-hil: cannot load the bootloader %s: %s\n", bootloader_path, problem);
			return 2;
		}
		h->avr->reset_pc = start;
		h->avr->codeend = h->avr->flashend;
		h->bootloader = 1;
	}
	for (int k = 0; k < h->profile.count; k++)
		if (!strcmp(h->profile.regions[k].name, "control_tick"))
			h->control_entry = h->profile.regions[k].entry_address;
	fflush(stdout);
	dup2(saved_stdout, STDOUT_FILENO);
	close(saved_stdout);
	board_attach_adc(h->avr, &h->plant);
	motion_attach(&h->motion, h->avr, &h->cycle, &h->last_core_cycle);
	serial_pty_attach(&h->serial, h->avr, seed);
	if (serial_pty_open(&h->serial) < 0) {
		fprintf(stderr, "phantom-hil: cannot create the pty or its link: %s\n", strerror(errno));
		return 2;
	}
	power_on(h);
	h->next_plant_cycle = h->plant_step_cycles;
	h->next_service_cycle = h->service_cycles;
	h->next_byte_cycle = h->byte_cycles;
	ask_realtime(h);
	reply("{\"ready\": true, \"mcu\": \"%s\", \"pty\": \"%s\", \"link\": \"%s\", \"scheduling\": \"%s\"}", mcu,
	      h->serial.slave_path, h->serial.link_path, h->scheduling);
	h->pace_origin_wall_s = h->busy_window_start_s = wall_seconds();
	h->pace_origin_cycle = 0;
	while (!h->quit)
		run_once(h);
	serial_pty_close(&h->serial);
	return 0;
}
