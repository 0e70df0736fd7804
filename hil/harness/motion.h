/* The scanner's stepper drivers seen from the simulator: the STEP, DIR and EN pins of two axes (the pin map of
   firmware/src/board_pins.h), each pulse counted into its axis's position and angle as a driver would (only
   while EN is low), the pulse timing checked against the drivers' datasheets, and a home switch driven onto
   each home input from the axis's angle. */
#ifndef PHANTOM_HIL_MOTION_H
#define PHANTOM_HIL_MOTION_H

#include <stdint.h>
#include <stdio.h>

#include "sim_avr.h"

#define MOTION_AXES 2
/* Pulses logged per axis (time and direction) until `motion reset`; later ones are counted, not logged. */
#define MOTION_LOG_CAPACITY (1u << 20)

typedef struct motion_pin {
	char port;                    /* 'A'..'D' */
	uint8_t bit;
} motion_pin_t;

struct motion;

typedef struct motion_axis {
	struct motion *motion;
	motion_pin_t step, dir, en, home;
	double steps_per_rev;         /* of the simulated mechanism; 0: unknown (no angle) */
	double start_deg;             /* its angle at step count 0 */
	int64_t steps;                /* +1 per pulse with DIR high, -1 with DIR low, while EN is low */
	uint64_t pulses;              /* pulses the driver took */
	uint64_t pulses_while_released;  /* pulses while EN was high or floating (a driver ignores them) */
	int step_level, dir_level;
	uint64_t last_rise, last_fall, last_dir_change;  /* harness cycles; 0: none yet */
	uint64_t min_high, min_low, min_setup, min_hold, min_interval;  /* cycles; UINT64_MAX: none yet */
	uint64_t *log_cycle;          /* the logged pulses' rising edges */
	int8_t *log_direction;        /* and their directions (+1, -1) */
	size_t logged;
	double released_since_s;      /* since when the driver is released (EN high or floating); < 0 while enabled */
	int switch_wired;
	double switch_low_deg, switch_high_deg;  /* the switch is active while the angle is inside */
	int switch_active_high;       /* its input's level when active */
} motion_axis_t;

typedef struct motion {
	avr_t *avr;
	const uint64_t *cycle;        /* the harness's running cycle count ... */
	const uint64_t *core_cycle;   /* ... and the core's cycle count it was taken at */
	motion_axis_t axes[MOTION_AXES];
} motion_t;

/* Wire the axes to the MCU's pins (by its name: atmega328p or atmega2560); cycle and core_cycle give the time. */
void motion_attach(motion_t *motion, avr_t *avr, const uint64_t *cycle, const uint64_t *core_cycle);

/* Forget the pulse counters, timing minima and logs (the positions stay). */
void motion_reset_counters(motion_t *motion);

/* Every plant step: drive each wired home switch's input from its axis's angle, and note when a driver was
   released (now_s: simulated time). */
void motion_step(motion_t *motion, double now_s);

/* The axis's angle (deg), or NAN when its steps per turn are unknown. */
double motion_angle_deg(const motion_axis_t *axis);

/* Whether the axis's driver is enabled: EN an output, driven low (an input floats high on the EN pull-up). */
int motion_enabled(const motion_axis_t *axis);

/* Set or remove (wired = 0) an axis's simulated home switch. */
void motion_set_switch(motion_axis_t *axis, int wired, double low_deg, double high_deg, int active_high);

/* Write the axis's logged pulses to a file: records of (uint64 harness cycle, int8 direction), little endian;
   returns the count written, or -1. */
long motion_write_log(const motion_axis_t *axis, const char *path);

/* JSON of each axis's position for `state`, and of everything for `motion`. */
void motion_format_positions(const motion_t *motion, char *out, size_t size);
void motion_format_details(const motion_t *motion, char *out, size_t size);

#endif
