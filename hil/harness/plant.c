#include "plant.h"

#include <math.h>
#include <stdio.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

/* One named parameter: a scalar (count 1), a vector (count 3) or the 3x3 matrix (count 9). */
typedef struct param_entry {
	const char *name;
	size_t offset;
	int count;
} param_entry_t;

#define PARAM(field, n) {#field, offsetof(plant_params_t, field), n}
static const param_entry_t param_table[] = {
	PARAM(atmospheric_pressure_pa, 1),
	PARAM(rest_volume_m3, 3),
	PARAM(compliance_m3_per_pa, 9),
	PARAM(free_flow_m3_per_s, 3),
	PARAM(blocked_pressure_pa, 3),
	PARAM(driver_threshold, 3),
	PARAM(leak_conductance_m3_per_s_per_pa, 3),
	PARAM(sensor_supply_v, 1),
	PARAM(sensor_gain_per_pa, 1),
	PARAM(sensor_offset_pa, 3),
	PARAM(sensor_noise_v, 1),
	PARAM(sensor_response_time_s, 1),
	PARAM(step_s, 1),
	PARAM(truth_step_pa, 1),
	PARAM(truth_volume_m3, PLANT_TRUTH_POINTS * PLANT_TRUTH_POINTS * PLANT_TRUTH_POINTS * PLANT_CHAMBERS),
};
#define PARAM_COUNT (sizeof(param_table) / sizeof(param_table[0]))

void plant_unset_params(plant_params_t *params)
{
	double *values = (double *)params;
	for (size_t k = 0; k < sizeof(*params) / sizeof(double); k++)
		values[k] = NAN;
}

int plant_set_param(plant_params_t *params, const char *name, double value)
{
	for (size_t k = 0; k < PARAM_COUNT; k++) {
		const param_entry_t *entry = &param_table[k];
		size_t length = strlen(entry->name);
		if (strncmp(name, entry->name, length))
			continue;
		const char *rest = name + length;
		int index = 0;
		if (entry->count == 1 && *rest)
			continue;
		if (entry->count == 3) {
			if (rest[0] != '.' || rest[1] < '0' || rest[1] > '2' || rest[2])
				continue;
			index = rest[1] - '0';
		}
		if (entry->count == 9) {
			if (rest[0] != '.' || rest[1] < '0' || rest[1] > '2' || rest[2] != '.' || rest[3] < '0' || rest[3] > '2'
			    || rest[4])
				continue;
			index = 3 * (rest[1] - '0') + (rest[3] - '0');
		}
		if (entry->count > 9) { /* a table: NAME.FLAT_INDEX (C order) */
			char *end;
			long flat = rest[0] == '.' ? strtol(rest + 1, &end, 10) : -1;
			if (flat < 0 || flat >= entry->count || end == rest + 1 || *end)
				continue;
			index = (int)flat;
		}
		((double *)((char *)params + entry->offset))[index] = value;
		return 0;
	}
	return -1;
}

const char *plant_check_params(const plant_params_t *params)
{
	static char message[160];
	for (size_t k = 0; k < PARAM_COUNT; k++) {
		const double *values = (const double *)((const char *)params + param_table[k].offset);
		for (int i = 0; i < param_table[k].count; i++)
			if (!isfinite(values[i])) {
				snprintf(message, sizeof(message), "plant parameter %s is missing or not finite", param_table[k].name);
				return message;
			}
	}
	if (!(params->atmospheric_pressure_pa > 0))
		return "atmospheric_pressure_pa must be positive";
	if (!(params->step_s > 0 && params->step_s <= 1e-3))
		return "step_s must be in (0, 1 ms]";
	if (!(params->sensor_supply_v > 0) || !(params->sensor_gain_per_pa > 0))
		return "sensor_supply_v and sensor_gain_per_pa must be positive";
	if (params->truth_step_pa < 0)
		return "truth_step_pa must not be negative (0: no truth table)";
	if (params->sensor_noise_v < 0 || params->sensor_response_time_s < 0)
		return "sensor_noise_v and sensor_response_time_s must not be negative";
	for (int i = 0; i < PLANT_CHAMBERS; i++) {
		if (!(params->rest_volume_m3[i] > 0))
			return "rest_volume_m3 must be positive";
		if (params->free_flow_m3_per_s[i] < 0 || !(params->blocked_pressure_pa[i] > 0))
			return "free_flow_m3_per_s must not be negative and blocked_pressure_pa must be positive";
		if (!(params->driver_threshold[i] >= 0 && params->driver_threshold[i] < 1))
			return "driver_threshold must be in [0, 1)";
		if (params->leak_conductance_m3_per_s_per_pa[i] < 0)
			return "leak_conductance_m3_per_s_per_pa must not be negative";
		if (!(params->compliance_m3_per_pa[i][i] >= 0))
			return "the compliance matrix's diagonal must not be negative";
		for (int j = 0; j < PLANT_CHAMBERS; j++)
			if (params->compliance_m3_per_pa[i][j] != params->compliance_m3_per_pa[j][i])
				return "the compliance matrix must be symmetric";
	}
	return NULL;
}

/* xorshift64*: a small deterministic generator for the sensor noise. */
static double uniform_open(uint64_t *state)
{
	uint64_t x = *state;
	x ^= x >> 12;
	x ^= x << 25;
	x ^= x >> 27;
	*state = x;
	return ((double)((x * 0x2545F4914F6CDD1DULL) >> 11) + 0.5) / 9007199254740992.0;
}

/* A standard normal deviate (Box-Muller). */
static double standard_normal(uint64_t *state)
{
	double u1 = uniform_open(state), u2 = uniform_open(state);
	return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

void plant_init(plant_t *plant, const plant_params_t *params, uint64_t seed)
{
	memset(plant, 0, sizeof(*plant));
	plant->params = *params;
	for (int i = 0; i < PLANT_CHAMBERS; i++)
		plant->stuck_drive_level[i] = -1.0;
	plant->rng_state = seed * 0x9E3779B97F4A7C15ULL + 0x2545F4914F6CDD1DULL;
	if (!plant->rng_state)
		plant->rng_state = 1;
}

double plant_effective_drive(const plant_t *plant, int chamber)
{
	double level = plant->stuck_drive_level[chamber] >= 0 ? plant->stuck_drive_level[chamber]
	                                                      : plant->drive_level[chamber];
	return level < 0 ? 0 : (level > 1 ? 1 : level);
}

/*
 * The blower through its driver (docs/hardware.md): the 62.5 kHz PWM, RC-filtered (its 1 ms lag is neglected
 * beside the chambers' time constants of 0.3 s and more), sets the amplitude of the driver's resonant drive,
 * which starts at driver_threshold: amplitude a = (u - u0) / (1 - u0) in [0, 1]. A piezo diaphragm's stroke
 * follows its drive amplitude, so both the free flow and the blocked pressure scale with a:
 * Q = Q_max a (1 - p / (p_blocked a)) = Q_max (a - p / p_blocked), never negative (a valveless blower that
 * is outpushed leaks back, which the back-leak term carries).
 */
double plant_blower_flow_m3_per_s(const plant_t *plant, int chamber, double pressure_pa)
{
	const plant_params_t *k = &plant->params;
	double threshold = k->driver_threshold[chamber];
	double amplitude = (plant_effective_drive(plant, chamber) - threshold) / (1.0 - threshold);
	if (amplitude <= 0)
		return 0.0;
	double flow_m3_per_s = k->free_flow_m3_per_s[chamber] * (amplitude - pressure_pa / k->blocked_pressure_pa[chamber]);
	return flow_m3_per_s > 0 ? flow_m3_per_s : 0.0;
}

/* Solve the 3x3 system a x = b by Gaussian elimination with partial pivoting. */
static void solve3(double a[3][3], double b[3], double x[3])
{
	for (int col = 0; col < 3; col++) {
		int pivot = col;
		for (int row = col + 1; row < 3; row++)
			if (fabs(a[row][col]) > fabs(a[pivot][col]))
				pivot = row;
		for (int k = 0; k < 3; k++) {
			double t = a[col][k]; a[col][k] = a[pivot][k]; a[pivot][k] = t;
		}
		double t = b[col]; b[col] = b[pivot]; b[pivot] = t;
		for (int row = col + 1; row < 3; row++) {
			double factor = a[row][col] / a[col][col];
			for (int k = col; k < 3; k++)
				a[row][k] -= factor * a[col][k];
			b[row] -= factor * b[col];
		}
	}
	for (int row = 2; row >= 0; row--) {
		double sum = b[row];
		for (int k = row + 1; k < 3; k++)
			sum -= a[row][k] * x[k];
		x[row] = sum / a[row][row];
	}
}

/*
 * Air volumes V(p) (m^3) and their derivatives dV_i/dp_j (m^3/Pa): the truth table, trilinear in the cell
 * that holds p (the edge cell extended beyond the grid), or the linear V0 + C p without a table.
 */
static void chamber_volumes_and_compliance(const plant_params_t *k, const double p_pa[PLANT_CHAMBERS],
                                           double volumes_m3[PLANT_CHAMBERS],
                                           double compliance_m3_per_pa[PLANT_CHAMBERS][PLANT_CHAMBERS])
{
	if (!(k->truth_step_pa > 0)) {
		for (int i = 0; i < PLANT_CHAMBERS; i++) {
			volumes_m3[i] = k->rest_volume_m3[i];
			for (int j = 0; j < PLANT_CHAMBERS; j++) {
				volumes_m3[i] += k->compliance_m3_per_pa[i][j] * p_pa[j];
				compliance_m3_per_pa[i][j] = k->compliance_m3_per_pa[i][j];
			}
		}
		return;
	}
	int cell[3];
	double fraction[3];
	for (int a = 0; a < 3; a++) {
		double x = p_pa[a] / k->truth_step_pa;
		int c = (int)floor(x);
		c = c < 0 ? 0 : (c > PLANT_TRUTH_POINTS - 2 ? PLANT_TRUTH_POINTS - 2 : c);
		cell[a] = c;
		fraction[a] = x - c;
	}
	for (int i = 0; i < PLANT_CHAMBERS; i++) {
		volumes_m3[i] = k->rest_volume_m3[i] - k->truth_volume_m3[0][0][0][i];
		for (int j = 0; j < PLANT_CHAMBERS; j++)
			compliance_m3_per_pa[i][j] = 0;
	}
	for (int corner = 0; corner < 8; corner++) {
		int bit[3] = {corner & 1, (corner >> 1) & 1, (corner >> 2) & 1};
		double factor[3], slope[3];
		for (int a = 0; a < 3; a++) {
			factor[a] = bit[a] ? fraction[a] : 1.0 - fraction[a];
			slope[a] = (bit[a] ? 1.0 : -1.0) / k->truth_step_pa;
		}
		const double *value = k->truth_volume_m3[cell[0] + bit[0]][cell[1] + bit[1]][cell[2] + bit[2]];
		for (int i = 0; i < PLANT_CHAMBERS; i++) {
			volumes_m3[i] += factor[0] * factor[1] * factor[2] * value[i];
			compliance_m3_per_pa[i][0] += slope[0] * factor[1] * factor[2] * value[i];
			compliance_m3_per_pa[i][1] += factor[0] * slope[1] * factor[2] * value[i];
			compliance_m3_per_pa[i][2] += factor[0] * factor[1] * slope[2] * value[i];
		}
	}
}

/*
 * Isothermal gas in coupled compliant chambers: the air in chamber i, (p_atm + p_i) V_i with
 * V = V0 + C p, changes by p_atm q_i where q_i is the net inflow at atmospheric conditions, so
 * sum_j [V_i delta_ij + (p_atm + p_i) C_ij] dp_j/dt = p_atm q_i.
 */
void plant_pressure_rate(const plant_t *plant, const double p_pa[PLANT_CHAMBERS], double rate_pa_per_s[PLANT_CHAMBERS])
{
	const plant_params_t *k = &plant->params;
	double matrix[3][3], rhs[3], volumes_m3[3], compliance[3][3];
	chamber_volumes_and_compliance(k, p_pa, volumes_m3, compliance);
	for (int i = 0; i < PLANT_CHAMBERS; i++) {
		for (int j = 0; j < PLANT_CHAMBERS; j++)
			matrix[i][j] = (k->atmospheric_pressure_pa + p_pa[i]) * compliance[i][j];
		matrix[i][i] += volumes_m3[i];
		double blower_m3_per_s = plant_blower_flow_m3_per_s(plant, i, p_pa[i]);
		double leak_m3_per_s = (k->leak_conductance_m3_per_s_per_pa[i] + plant->fault_leak_m3_per_s_per_pa[i]) * p_pa[i];
		rhs[i] = k->atmospheric_pressure_pa * (blower_m3_per_s - leak_m3_per_s);
	}
	solve3(matrix, rhs, rate_pa_per_s);
}

void plant_step(plant_t *plant, double dt_s)
{
	double k1[3], k2[3], k3[3], k4[3], probe[3];
	const double *p = plant->pressure_pa;
	plant_pressure_rate(plant, p, k1);
	for (int i = 0; i < 3; i++) probe[i] = p[i] + 0.5 * dt_s * k1[i];
	plant_pressure_rate(plant, probe, k2);
	for (int i = 0; i < 3; i++) probe[i] = p[i] + 0.5 * dt_s * k2[i];
	plant_pressure_rate(plant, probe, k3);
	for (int i = 0; i < 3; i++) probe[i] = p[i] + dt_s * k3[i];
	plant_pressure_rate(plant, probe, k4);
	double tau_s = plant->params.sensor_response_time_s;
	double blend = tau_s > 0 ? 1.0 - exp(-dt_s / tau_s) : 1.0;
	for (int i = 0; i < 3; i++) {
		plant->pressure_pa[i] += dt_s * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]) / 6.0;
		double at_port_pa = plant->tube_off[i] ? 0.0 : plant->pressure_pa[i];
		plant->sensed_pressure_pa[i] += blend * (at_port_pa - plant->sensed_pressure_pa[i]);
	}
	plant->time_s += dt_s;
}

void plant_chamber_volumes(const plant_t *plant, double volumes_m3[PLANT_CHAMBERS])
{
	double compliance[3][3];
	chamber_volumes_and_compliance(&plant->params, plant->pressure_pa, volumes_m3, compliance);
}

/* MPXV7025G: Vout = Vs (0.018 P[kPa] + 0.5), clipped to the rails, plus noise; a cut wire reads 0 V. */
double plant_sensor_voltage(plant_t *plant, int chamber)
{
	const plant_params_t *k = &plant->params;
	if (plant->sensor_cut[chamber])
		return 0.0;
	double pressure_pa = plant->sensed_pressure_pa[chamber] + k->sensor_offset_pa[chamber];
	double volts = k->sensor_supply_v * (k->sensor_gain_per_pa * pressure_pa + 0.5);
	volts += k->sensor_noise_v * standard_normal(&plant->rng_state);
	if (volts < 0)
		volts = 0;
	if (volts > k->sensor_supply_v)
		volts = k->sensor_supply_v;
	return volts;
}
