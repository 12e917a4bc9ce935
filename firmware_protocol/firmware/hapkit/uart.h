/*
 * uart.h -- interrupt-driven USART0 for the Hapkit firmware (ATmega328P): fixed rings, no
 * malloc. The receive ring is filled by the RX interrupt and drained by the main loop; the
 * transmit ring is filled by the main loop and drained by the data-register-empty
 * interrupt.
 */
#ifndef HK_UART_H
#define HK_UART_H

#include <stdint.h>
#include <stddef.h>

#ifndef HK_BAUD
#define HK_BAUD 1000000UL /* 8N1; 16 MHz / (8 * (UBRR + 1)) with U2X: exact at 1 and 2 Mbaud */
#endif
#define HK_BITS_PER_BYTE 10u /* start + 8 data + stop */

void uart_init(void);
/* Next received byte into *b: 1, or 0 when none is waiting. */
uint8_t uart_get(uint8_t *b);
/* Whether received bytes are waiting (for the sleep decision, interrupts disabled). */
uint8_t uart_rx_pending(void);
/* Queue `len` bytes: 1, or 0 (nothing queued) when the ring has not room for all. */
uint8_t uart_put(const uint8_t *p, size_t len);
/* Bytes lost because the receive ring was full (each makes its frame fail its CRC). */
uint16_t uart_rx_lost(void);

#endif
