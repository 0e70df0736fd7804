#define _GNU_SOURCE
#include "serial_pty.h"

#include <errno.h>
#include <fcntl.h>
#include <pty.h>
#include <stdio.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "avr_uart.h"
#include "sim_io.h"

/* A uniform number in [0, 1) from xorshift64*. */
static double next_uniform(uint64_t *state)
{
	uint64_t x = *state;
	x ^= x >> 12;
	x ^= x << 25;
	x ^= x >> 27;
	*state = x;
	return (double)((x * 0x2545F4914F6CDD1DULL) >> 11) / 9007199254740992.0;
}

/* Apply line noise to one byte; returns -1 when the byte is lost. */
static int corrupt_byte(serial_pty_t *serial, uint8_t byte)
{
	if (serial->drop_probability > 0 && next_uniform(&serial->rng_state) < serial->drop_probability) {
		serial->bytes_dropped++;
		return -1;
	}
	if (serial->flip_probability > 0 && next_uniform(&serial->rng_state) < serial->flip_probability) {
		serial->bytes_flipped++;
		byte ^= (uint8_t)(1u << (int)(next_uniform(&serial->rng_state) * 8));
	}
	return byte;
}

/* Queue one byte for the host (lost if nobody is connected or the queue is full). */
static void queue_for_host(serial_pty_t *serial, uint8_t byte)
{
	if (serial->master_fd < 0)
		return;
	if (serial->from_mcu_count == SERIAL_QUEUE_SIZE) {
		serial->bytes_overflowed++;
		return;
	}
	serial->from_mcu[serial->from_mcu_count++] = byte;
}

/* Whether `fault drop_frame` loses the MCU's frame that starts with these two bytes: a frame is COBS(msg_id, seq,
   payload, crc) then 0x00, and a message id is never 0, so the COBS code comes first and the id second. */
static int drops_frame(serial_pty_t *serial, uint8_t second_byte)
{
	if (serial->drop_frames_left == 0 || second_byte != serial->drop_msg_id)
		return 0;
	serial->drop_frames_left--;
	serial->frames_dropped++;
	return 1;
}

/* The firmware wrote a byte to UDR0: queue it for the host. The queue is written out at the next service, a
   millisecond of board time at most: a write per byte was 1500 system calls a second of telemetry. While a
   `fault drop_frame` is armed, a frame's first byte waits for its second (the message id) to say whether the
   frame goes. */
static void on_uart_output(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	serial_pty_t *serial = param;
	serial->bytes_from_mcu++;
	uint8_t sent = (uint8_t)value;
	size_t position = serial->frame_position;
	serial->frame_position = sent == 0 ? 0 : position + 1;
	if (serial->dropping) {
		serial->bytes_dropped++;
		serial->dropping = sent != 0;
		return;
	}
	if (position == 0 && sent != 0 && serial->drop_frames_left > 0) {
		serial->held_code = sent;
		return;
	}
	if (serial->held_code >= 0) {
		uint8_t code = (uint8_t)serial->held_code;
		serial->held_code = -1;
		if (sent != 0 && drops_frame(serial, sent)) {
			serial->bytes_dropped += 2;
			serial->dropping = 1;
			return;
		}
		int byte = corrupt_byte(serial, code);
		if (byte >= 0)
			queue_for_host(serial, (uint8_t)byte);
	}
	int byte = corrupt_byte(serial, sent);
	if (byte >= 0)
		queue_for_host(serial, (uint8_t)byte);
}

/* Write the queued bytes to the pty; what it does not take (the host stopped reading) is lost. */
static void flush_output(serial_pty_t *serial)
{
	if (serial->from_mcu_count == 0)
		return;
	ssize_t written = write(serial->master_fd, serial->from_mcu, serial->from_mcu_count);
	size_t taken = written > 0 ? (size_t)written : 0;
	serial->bytes_overflowed += serial->from_mcu_count - taken;
	serial->from_mcu_count = 0;
}

/* The UART's receive FIFO has room again. */
static void on_uart_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	((serial_pty_t *)param)->uart_full = 0;
}

/* The UART's receive FIFO is full. */
static void on_uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	((serial_pty_t *)param)->uart_full = 1;
}

void serial_pty_attach(serial_pty_t *serial, avr_t *avr, uint64_t seed)
{
	uint32_t flags = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
	flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), on_uart_output, serial);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), on_uart_xon, serial);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), on_uart_xoff, serial);
	serial->uart_input = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	serial->rng_state = seed * 0xD1B54A32D192ED03ULL + 0x9E3779B97F4A7C15ULL;
}

int serial_pty_open(serial_pty_t *serial)
{
	struct termios raw;
	if (openpty(&serial->master_fd, &serial->slave_fd, serial->slave_path, NULL, NULL) < 0)
		return -1;
	tcgetattr(serial->slave_fd, &raw);
	cfmakeraw(&raw);
	tcsetattr(serial->slave_fd, TCSANOW, &raw);
	fcntl(serial->master_fd, F_SETFL, fcntl(serial->master_fd, F_GETFL) | O_NONBLOCK);
	fcntl(serial->master_fd, F_SETFD, FD_CLOEXEC);
	fcntl(serial->slave_fd, F_SETFD, FD_CLOEXEC);
	if (serial->link_path[0]) {
		char temporary[600];
		snprintf(temporary, sizeof(temporary), "%s.new", serial->link_path);
		unlink(temporary);
		if (symlink(serial->slave_path, temporary) < 0 || rename(temporary, serial->link_path) < 0)
			return -1;
	}
	return 0;
}

void serial_pty_close(serial_pty_t *serial)
{
	if (serial->link_path[0])
		unlink(serial->link_path);
	if (serial->master_fd >= 0)
		close(serial->master_fd);
	if (serial->slave_fd >= 0)
		close(serial->slave_fd);
	serial->master_fd = serial->slave_fd = -1;
	serial->slave_path[0] = 0;
	serial->to_mcu_count = 0;
	serial->from_mcu_count = 0;
	serial->held_code = -1;  /* a frame cut by the unplug is not finished after it: the next starts afresh */
	serial->dropping = 0;
	serial->frame_position = 0;
}

void serial_pty_poll(serial_pty_t *serial)
{
	uint8_t buffer[256];
	if (serial->master_fd < 0)
		return;
	flush_output(serial);
	for (;;) {
		size_t room = SERIAL_QUEUE_SIZE - serial->to_mcu_count;
		if (room == 0)
			return;
		ssize_t got = read(serial->master_fd, buffer, room < sizeof(buffer) ? room : sizeof(buffer));
		if (got <= 0)
			return;
		for (ssize_t k = 0; k < got; k++) {
			int byte = corrupt_byte(serial, buffer[k]);
			if (byte < 0)
				continue;
			serial->to_mcu[(serial->to_mcu_head + serial->to_mcu_count) % SERIAL_QUEUE_SIZE] = (uint8_t)byte;
			serial->to_mcu_count++;
		}
	}
}

int serial_pty_wants_input(const serial_pty_t *serial)
{
	return serial->master_fd >= 0 && serial->to_mcu_count < SERIAL_QUEUE_SIZE;
}

int serial_pty_feed(serial_pty_t *serial)
{
	if (serial->to_mcu_count == 0 || serial->uart_full)
		return 0;
	uint8_t byte = serial->to_mcu[serial->to_mcu_head];
	serial->to_mcu_head = (serial->to_mcu_head + 1) % SERIAL_QUEUE_SIZE;
	serial->to_mcu_count--;
	serial->bytes_to_mcu++;
	avr_raise_irq(serial->uart_input, byte);
	return 1;
}
