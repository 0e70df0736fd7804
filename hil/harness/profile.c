#include "profile.h"

#include <stdlib.h>
#include <string.h>

int profile_add(profile_t *profile, const char *spec)
{
	const char *equals = strchr(spec, '=');
	if (!equals || equals == spec || profile->count >= PROFILE_MAX_REGIONS)
		return -1;
	size_t length = (size_t)(equals - spec);
	if (length >= sizeof(profile->regions[0].name))
		return -1;
	char *end;
	unsigned long address = strtoul(equals + 1, &end, 0);
	unsigned long long min_cycles = 0;
	if (end == equals + 1)
		return -1;
	if (*end == ':') {
		char *start = end + 1;
		min_cycles = strtoull(start, &end, 0);
		if (end == start)
			return -1;
	}
	if (*end)
		return -1;
	profile_region_t *region = &profile->regions[profile->count++];
	memset(region, 0, sizeof(*region));
	memcpy(region->name, spec, length);
	region->entry_address = (uint32_t)address;
	region->min_cycles = min_cycles;
	uint32_t word = region->entry_address >> 1;
	if (word < PROFILE_FLASH_WORDS)
		profile->entries[word >> 3] |= (uint8_t)(1u << (word & 7));
	return 0;
}

void profile_check(profile_t *profile, avr_t *avr, uint64_t cycle)
{
	uint16_t sp = (uint16_t)(avr->data[R_SPL] | (avr->data[R_SPH] << 8));
	if (sp < profile->min_sp)
		profile->min_sp = sp;
	if (profile->any_active)
		profile->busy_cycles += cycle - profile->last_cycle;
	profile->last_cycle = cycle;
	/* Called after every instruction: nothing changes unless the PC is at a region's entry or SP rose above an
	   active region's entry SP (its return), so those two tests come first and the regions are looked at only
	   then (the loop over them was a tenth of the harness's time). */
	uint32_t word = avr->pc >> 1;
	int at_entry = word < PROFILE_FLASH_WORDS && (profile->entries[word >> 3] >> (word & 7)) & 1;
	if (!at_entry && !(profile->any_active && sp > profile->lowest_entry_sp))
		return;
	int any_active = 0;
	uint16_t lowest_entry_sp = 0xFFFF;
	for (int k = 0; k < profile->count; k++) {
		profile_region_t *region = &profile->regions[k];
		if (!region->active) {
			if (avr->pc == region->entry_address) {
				region->active = 1;
				region->entry_sp = sp;
				region->start_cycle = cycle;
			}
		} else if (sp > region->entry_sp) {
			uint64_t spent = cycle - region->start_cycle;
			region->active = 0;
			if (spent < region->min_cycles) {
				region->short_calls++;
			} else {
				region->calls++;
				region->total_cycles += spent;
				if (spent > region->max_cycles)
					region->max_cycles = spent;
			}
		}
		if (region->active) {
			any_active = 1;
			if (region->entry_sp < lowest_entry_sp)
				lowest_entry_sp = region->entry_sp;
		}
	}
	profile->any_active = any_active;
	profile->lowest_entry_sp = lowest_entry_sp;
}

void profile_reset(profile_t *profile, uint64_t cycle)
{
	for (int k = 0; k < profile->count; k++) {
		profile_region_t *region = &profile->regions[k];
		region->calls = region->total_cycles = region->max_cycles = region->short_calls = 0;
		region->active = 0;
	}
	profile->since_cycle = profile->last_cycle = cycle;
	profile->busy_cycles = 0;
	profile->any_active = 0;
	profile->min_sp = 0xFFFF;
}

void profile_abort(profile_t *profile)
{
	for (int k = 0; k < profile->count; k++)
		profile->regions[k].active = 0;
	profile->any_active = 0;
}
