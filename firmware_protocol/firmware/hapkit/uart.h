/*
 * uart.h -- interrupt-driven USART0 for the Hapkit firmware (ATmega328P): fixed buffers, no
 * malloc.
 *
 * Receive: the RX interrupt puts the bytes in a 256-byte ring and counts the 0x00
 * delimiters, so the main loop is woken for a frame, not for each byte (at 2 Mbaud a byte
 * comes every 80 cycles), and a backlog of frames (say garbage, then a FORCE) waits in
 * the ring while the main loop works on a tick. A frame longer than HP_MAX_FRAME - 1 bytes
 * is reported as over-long (length UART_OVERLONG); a byte arriving with the ring full is
 * lost and counted (uart_rx_lost).
 * Transmit: a ring drained by the data-register-empty interrupt.
 */
#ifndef HK_UART_H
#define HK_UART_H

#include <stddef.h>
#include <stdint.h>

#ifndef HK_BAUD
#define HK_BAUD 2000000UL /* 8N1; 16 MHz / (8 * (UBRR + 1)) with U2X: exact at 1 and 2 Mbaud */
#endif
#define HK_BITS_PER_BYTE 10u /* start + 8 data + stop */
#define UART_FRAME_MAX 127u  /* COBS bytes of the largest frame (HP_MAX_FRAME - 1) */
#define UART_OVERLONG 0xFFu  /* frame length reported for an over-long frame */

void uart_init(void);
/* Whether a received frame waits (cheap: for the sleep decision, interrupts disabled). */
uint8_t uart_frame_ready(void);
/* The waiting frame: its COBS bytes without the delimiter in *frame, and its length
 * (1..UART_FRAME_MAX, or UART_OVERLONG); 0 when none waits. Release it with
 * uart_frame_done() before the next call. */
uint8_t uart_frame(const uint8_t **frame);
void uart_frame_done(void);
/* Queue `len` bytes: 1, or 0 (nothing queued) when the ring has not room for all. */
uint8_t uart_put(const uint8_t *p, size_t len);
/* Queue the frame of packet `pk` (type | body | crc, `len` <= 253 bytes): COBS-encoded
 * straight into the ring, then the 0x00 delimiter (hp_cobs_encode's bytes, without the
 * copy through a frame buffer). 1, or 0 (nothing queued) when the ring has not room. */
uint8_t uart_put_packet(const uint8_t *pk, uint8_t len);
/* The waiting frame, COBS-decoded as it is taken from the ring into `pk` (room for
 * HP_MAX_PACKET bytes): its packet length (1..HP_MAX_PACKET); 0 when none waits (empty
 * frames are idle fill, skipped); UART_OVERLONG for a frame longer than UART_FRAME_MAX;
 * UART_BAD_COBS for a COBS error (a code byte pointing past the delimiter). The same
 * results as uart_frame + hp_cobs_decode, in one pass over the bytes. */
uint8_t uart_packet(uint8_t *pk);
#define UART_BAD_COBS 0xFEu
/* Bytes lost because the ring was full (each spoils its frame, which fails its CRC). */
uint16_t uart_rx_lost(void);

#endif
