/* The pneumatic plant of the phantom's three chambers, integrated at a fixed step in simulated time. */
#ifndef PHANTOM_HIL_PLANT_H
#define PHANTOM_HIL_PLANT_H

#include <stdint.h>

#define PLANT_CHAMBERS 3
/* Points per pressure axis of the truth table (chamber volumes over the three pressures). */
#define PLANT_TRUTH_POINTS 4

/* Plant parameters, all SI (Pa, m^3, m^3/s, V, s). Filled from hil/plant.toml by the Python side. */
typedef struct plant_params {
	double atmospheric_pressure_pa;
	double rest_volume_m3[PLANT_CHAMBERS];
	double compliance_m3_per_pa[PLANT_CHAMBERS][PLANT_CHAMBERS];
	double free_flow_m3_per_s[PLANT_CHAMBERS];
	double blocked_pressure_pa[PLANT_CHAMBERS];
	double driver_threshold[PLANT_CHAMBERS];     /* drive level below which the blower's driver does not run */
	double leak_conductance_m3_per_s_per_pa[PLANT_CHAMBERS];
	double sensor_supply_v;
	double sensor_gain_per_pa;        /* MPXV7025G: 0.018 per kPa, as a fraction of the supply */
	double sensor_offset_pa[PLANT_CHAMBERS];
	double sensor_noise_v;            /* standard deviation of white noise on the output */
	double sensor_response_time_s;    /* first-order lag of the sensor */
	double step_s;                    /* fixed integration step */
	/* The truth's pressure-volume behaviour: each chamber's volume (m^3) at pressures (i, j, k) truth_step_pa on
	 * a grid, interpolated trilinearly (the edge cells extended beyond it), air volume = rest_volume_m3 +
	 * truth(p) - truth(0). truth_step_pa = 0: no table, V = rest_volume_m3 + compliance_m3_per_pa p. */
	double truth_step_pa;
	double truth_volume_m3[PLANT_TRUTH_POINTS][PLANT_TRUTH_POINTS][PLANT_TRUTH_POINTS][PLANT_CHAMBERS];
} plant_params_t;

/* Plant state and the faults injected into it. */
typedef struct plant {
	plant_params_t params;
	double time_s;
	double pressure_pa[PLANT_CHAMBERS];
	double sensed_pressure_pa[PLANT_CHAMBERS];
	double drive_level[PLANT_CHAMBERS];          /* what the firmware commands, in [0, 1] */
	double stuck_drive_level[PLANT_CHAMBERS];    /* < 0: not stuck */
	double fault_leak_m3_per_s_per_pa[PLANT_CHAMBERS];
	int sensor_cut[PLANT_CHAMBERS];
	int tube_off[PLANT_CHAMBERS];                /* the sensor's tube is off: it reads the room, not the chamber */
	uint64_t rng_state;
} plant_t;

/* Set the plant to rest (vented chambers, no faults) with the given parameters and noise seed. */
void plant_init(plant_t *plant, const plant_params_t *params, uint64_t seed);

/* Set a parameter by its SI name ("rest_volume_m3.1", "compliance_m3_per_pa.0.2", ...); 0 on success. */
int plant_set_param(plant_params_t *params, const char *name, double value);

/* Mark every parameter unset (NaN): the harness has no defaults, hil/plant.toml is the one source. */
void plant_unset_params(plant_params_t *params);

/* Check the parameters make physical sense; returns NULL or a message saying what is wrong. */
const char *plant_check_params(const plant_params_t *params);

/* Advance the plant by dt_s with the current drive levels (RK4 on the pressures). */
void plant_step(plant_t *plant, double dt_s);

/* The pressure derivative dp/dt (Pa/s) at pressures p_pa with the current drive and faults. */
void plant_pressure_rate(const plant_t *plant, const double p_pa[PLANT_CHAMBERS], double rate_pa_per_s[PLANT_CHAMBERS]);

/* Chamber air volumes (m^3): from the truth table, else V0 + C p. */
void plant_chamber_volumes(const plant_t *plant, double volumes_m3[PLANT_CHAMBERS]);

/* The sensor's output voltage (V) for one chamber, with noise, offset and a cut wire. */
double plant_sensor_voltage(plant_t *plant, int chamber);

/* Air a blower delivers (m^3/s at atmospheric conditions) against a gauge pressure, for its drive level. */
double plant_blower_flow_m3_per_s(const plant_t *plant, int chamber, double pressure_pa);

/* The drive level the blower actually sees (stuck or commanded). */
double plant_effective_drive(const plant_t *plant, int chamber);

#endif
