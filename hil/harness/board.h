/* The Board contract seen from the simulator: sensors into the ADC, blower drive out of the PWM timers. */
#ifndef PHANTOM_HIL_BOARD_H
#define PHANTOM_HIL_BOARD_H

#include "plant.h"
#include "sim_avr.h"

/* Feed ADC channels 0..2 from the plant's sensor voltages, just in time for each conversion. */
void board_attach_adc(avr_t *avr, plant_t *plant);

/* Read the drive level of each chamber's blower from the timer registers (OCR / TOP, 0 when disconnected). */
void board_read_drive_levels(const avr_t *avr, double levels[PLANT_CHAMBERS]);

#endif
