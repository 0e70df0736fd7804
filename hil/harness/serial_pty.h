/* The board's USART0 as a pseudo-terminal, with optional line noise in both directions. */
#ifndef PHANTOM_HIL_SERIAL_PTY_H
#define PHANTOM_HIL_SERIAL_PTY_H

#include <stdint.h>
#include <stddef.h>

#include "sim_avr.h"

#define SERIAL_QUEUE_SIZE 4096

typedef struct serial_pty {
	int master_fd;
	int slave_fd;                 /* held open so the pty survives the host closing it */
	char slave_path[128];
	char link_path[512];          /* stable symlink to slave_path; empty for none */
	uint8_t to_mcu[SERIAL_QUEUE_SIZE];
	size_t to_mcu_head, to_mcu_count;
	uint8_t from_mcu[SERIAL_QUEUE_SIZE];  /* the firmware's bytes not yet written to the pty */
	size_t from_mcu_count;
	int uart_full;                /* the UART's receive FIFO signalled XOFF */
	avr_irq_t *uart_input;
	double flip_probability;      /* per byte: one random bit flipped */
	double drop_probability;      /* per byte: the byte lost */
	uint64_t rng_state;
	/* `fault drop_frame`: the next drop_frames_left frames from the MCU whose message id is drop_msg_id are lost
	   whole (as a frame whose CRC fails is, but certainly and only that one) */
	int drop_msg_id;              /* -1: none */
	uint32_t drop_frames_left;
	size_t frame_position;        /* of the MCU's next byte in its frame (0: a frame starts) */
	int held_code;                /* a frame's first byte (COBS code), held until its message id is seen; -1 none */
	int dropping;                 /* the frame being sent is dropped up to its delimiter */
	uint64_t bytes_to_mcu, bytes_from_mcu, bytes_dropped, bytes_flipped, bytes_overflowed, frames_dropped;
} serial_pty_t;

/* Connect to the MCU's UART '0' IRQs; call once after the core is initialised. */
void serial_pty_attach(serial_pty_t *serial, avr_t *avr, uint64_t seed);

/* Create the pty (raw mode) and point link_path at it; returns 0 or -1 with errno. */
int serial_pty_open(serial_pty_t *serial);

/* Close the pty and remove the link, as a pulled USB cable does; queued bytes are lost. */
void serial_pty_close(serial_pty_t *serial);

/* Write the firmware's bytes out (what the pty does not take is lost, as on a full USB buffer), then move what
   the host wrote into the queue towards the MCU. */
void serial_pty_poll(serial_pty_t *serial);

/* Whether the host has written bytes the queue towards the MCU has room for (the pacing's wait ends then). */
int serial_pty_wants_input(const serial_pty_t *serial);

/* Hand one queued byte to the UART if it can take it (call once per byte time); 1 if a byte went. */
int serial_pty_feed(serial_pty_t *serial);

#endif
