/* The Board contract seen from the simulator: sensors into the ADC, blower drive out of the PWM timers. */
#ifndef PHANTOM_HIL_BOARD_H
#define PHANTOM_HIL_BOARD_H

#include "plant.h"
#include "sim_avr.h"

/* Feed ADC channels 0..2 from the plant's sensor voltages, just in time for each conversion. */
void board_attach_adc(avr_t *avr, plant_t *plant);

/* Read the drive level of each chamber's blower from the timer registers (OCR / TOP, 0 when disconnected). */
void board_read_drive_levels(const avr_t *avr, double levels[PLANT_CHAMBERS]);

/* What a blower pin is doing: an input without pull-up (floating: only an external pull-down holds the driver
   off), an input with pull-up, an output held low, an output held high, or connected to its PWM compare unit. */
typedef enum { PIN_FLOATING, PIN_PULLUP, PIN_LOW, PIN_HIGH, PIN_PWM } pin_mode_t;
extern const char *const pin_mode_names[];

/* The mode of each chamber's blower pin now (the pin map of firmware/src/board_pins.h). */
void board_blower_pin_modes(const avr_t *avr, pin_mode_t modes[PLANT_CHAMBERS]);

#endif
