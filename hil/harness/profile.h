/* Exact cycle counts of firmware functions, measured from the outside by watching PC and SP. */
#ifndef PHANTOM_HIL_PROFILE_H
#define PHANTOM_HIL_PROFILE_H

#include <stdint.h>

#include "sim_avr.h"

#define PROFILE_MAX_REGIONS 24
#define PROFILE_FLASH_WORDS (1u << 17)   /* the largest flash simavr runs here (ATmega2560: 256 KB) in words */

/* One function: counted from the cycle PC reaches its entry until SP rises above its entry value (return). */
typedef struct profile_region {
	char name[48];
	uint32_t entry_address;       /* byte address, as avr-nm prints it */
	uint64_t min_cycles;          /* shorter calls (early returns) are only counted in short_calls */
	int active;
	uint16_t entry_sp;
	uint64_t start_cycle;
	uint64_t calls, total_cycles, max_cycles, short_calls;
} profile_region_t;

typedef struct profile {
	profile_region_t regions[PROFILE_MAX_REGIONS];
	int count;
	uint64_t since_cycle;         /* counters cover [since_cycle, now) */
	uint64_t busy_cycles;         /* cycles during which at least one region was active (their union) */
	uint64_t last_cycle;
	int any_active;
	uint16_t min_sp;              /* the lowest stack pointer seen (the stack's deepest point) */
	uint16_t lowest_entry_sp;     /* the lowest entry SP of the active regions: none returns until SP rises above */
	uint8_t entries[PROFILE_FLASH_WORDS / 8];  /* a bit per flash word: a region's entry starts there */
} profile_t;

/* Add a region from "name=0xADDRESS" or "name=0xADDRESS:MIN_CYCLES"; 0 on success. */
int profile_add(profile_t *profile, const char *spec);

/* Look at the core after one instruction; cycle is the harness's running cycle count. */
void profile_check(profile_t *profile, avr_t *avr, uint64_t cycle);

/* Forget calls in progress (the core was reset: they never return). */
void profile_abort(profile_t *profile);

/* Zero the counters from this cycle on. */
void profile_reset(profile_t *profile, uint64_t cycle);

#endif
