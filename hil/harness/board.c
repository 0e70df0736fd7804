#include "board.h"

#include <math.h>
#include <string.h>

#include "avr_adc.h"
#include "sim_io.h"

/* Data-space addresses of the timer registers; the same on the ATmega328P and the ATmega2560. */
enum {
	TCCR1A = 0x80, ICR1L = 0x86, OCR1AL = 0x88, OCR1BL = 0x8A,
	TCCR2A = 0xB0, OCR2B = 0xB4,
};

typedef struct adc_binding {
	avr_t *avr;
	plant_t *plant;
} adc_binding_t;

static adc_binding_t adc_binding;

/* A conversion starts: give the selected channel the sensor's voltage at this instant. */
static void on_adc_trigger(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	adc_binding_t *binding = param;
	union {
		avr_adc_mux_t mux;
		uint32_t value;
	} event = {.value = value};
	if (event.mux.kind != ADC_MUX_SINGLE || event.mux.src >= PLANT_CHAMBERS)
		return;
	int chamber = event.mux.src;
	uint32_t millivolts = (uint32_t)lround(plant_sensor_voltage(binding->plant, chamber) * 1000.0);
	avr_raise_irq(avr_io_getirq(binding->avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + chamber), millivolts);
}

void board_attach_adc(avr_t *avr, plant_t *plant)
{
	adc_binding.avr = avr;
	adc_binding.plant = plant;
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_OUT_TRIGGER), on_adc_trigger,
	                        &adc_binding);
	for (int chamber = 0; chamber < PLANT_CHAMBERS; chamber++)
		avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + chamber),
		              (uint32_t)lround(plant_sensor_voltage(plant, chamber) * 1000.0));
}

/* OCR / TOP while the compare-output mode bits connect the pin, else 0. */
static double pwm_level(unsigned compare_mode, unsigned compare, unsigned top)
{
	if (compare_mode == 0 || top == 0)
		return 0.0;
	double level = (double)compare / (double)top;
	return level > 1.0 ? 1.0 : level;
}

void board_read_drive_levels(const avr_t *avr, double levels[PLANT_CHAMBERS])
{
	const uint8_t *data = avr->data;
	unsigned top1 = data[ICR1L] | (data[ICR1L + 1] << 8);
	levels[0] = pwm_level((data[TCCR1A] >> 6) & 3, data[OCR1AL] | (data[OCR1AL + 1] << 8), top1);
	levels[1] = pwm_level((data[TCCR1A] >> 4) & 3, data[OCR1BL] | (data[OCR1BL + 1] << 8), top1);
	levels[2] = pwm_level((data[TCCR2A] >> 4) & 3, data[OCR2B], 0xFF);
}

const char *const pin_mode_names[] = {"floating", "pullup", "low", "high", "pwm"};

/* Data-space addresses of DDRx (PORTx is the next one) and the bit of each blower pin, and the compare-output
   mode bits (TCCRnA address, shift) that connect it to its timer. */
typedef struct pin_location {
	uint16_t ddr;
	uint8_t bit;
	uint16_t tccr;
	uint8_t com_shift;
} pin_location_t;

static const pin_location_t uno_pins[PLANT_CHAMBERS] = {
	{0x24, 1, TCCR1A, 6}, {0x24, 2, TCCR1A, 4}, {0x2A, 3, TCCR2A, 4},  /* PB1, PB2, PD3 */
};
static const pin_location_t mega_pins[PLANT_CHAMBERS] = {
	{0x24, 5, TCCR1A, 6}, {0x24, 6, TCCR1A, 4}, {0x101, 6, TCCR2A, 4},  /* PB5, PB6, PH6 */
};

void board_blower_pin_modes(const avr_t *avr, pin_mode_t modes[PLANT_CHAMBERS])
{
	const pin_location_t *pins = strcmp(avr->mmcu, "atmega2560") ? uno_pins : mega_pins;
	const uint8_t *data = avr->data;
	for (int i = 0; i < PLANT_CHAMBERS; i++) {
		int output = (data[pins[i].ddr] >> pins[i].bit) & 1;
		int high = (data[pins[i].ddr + 1] >> pins[i].bit) & 1;
		int connected = (data[pins[i].tccr] >> pins[i].com_shift) & 3;
		if (!output)
			modes[i] = high ? PIN_PULLUP : PIN_FLOATING;
		else if (connected)
			modes[i] = PIN_PWM;
		else
			modes[i] = high ? PIN_HIGH : PIN_LOW;
	}
}
