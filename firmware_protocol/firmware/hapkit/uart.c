/* uart.c -- see uart.h. */
#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#define TX_SIZE 256u /* a STATE (31), a FAULT (11), a PONG (25), LINK + HELLO (10 + 43) */

static volatile uint8_t rx_ring[256];  /* bytes as received, delimiters included */
static volatile uint8_t rx_head, rx_tail; /* uint8_t: wraps at 256 */
static volatile uint8_t rx_frames;        /* delimiters in the ring not yet taken */
static volatile uint16_t rx_lost;
static uint8_t rx_frame[UART_FRAME_MAX];  /* the frame handed to the main loop */
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail; /* tail: read by the ISR; uint8_t wraps at 256 */

void uart_init(void)
{
    uint16_t ubrr = (uint16_t)(F_CPU / (8UL * HK_BAUD) - 1UL);
    /* frame format and U2X first: the line rate is taken when UBRR0L is written (so on
     * the chip, and so in simavr, which computes it at that write) */
    UCSR0A = (uint8_t)(1 << U2X0);
    UCSR0C = (uint8_t)((1 << UCSZ01) | (1 << UCSZ00)); /* 8N1 */
    UBRR0H = (uint8_t)(ubrr >> 8);
    UBRR0L = (uint8_t)ubrr;
    UCSR0B = (uint8_t)((1 << RXEN0) | (1 << TXEN0) | (1 << RXCIE0));
}

ISR(USART_RX_vect)
{
    uint8_t b = UDR0;
    uint8_t h = rx_head;
    uint8_t next = (uint8_t)(h + 1u);
    if (next == rx_tail) {
        rx_lost++; /* 255 bytes behind: the byte is lost, its frame fails its CRC */
        return;
    }
    rx_ring[h] = b;
    rx_head = next;
    if (b == 0) {
        rx_frames++; /* wake the main loop once per frame, not per byte */
    }
}

ISR(USART_UDRE_vect)
{
    uint8_t t = tx_tail;
    if (t == tx_head) {
        UCSR0B &= (uint8_t)~(1 << UDRIE0);
        return;
    }
    UDR0 = tx_buf[t];
    tx_tail = (uint8_t)(t + 1u);
}

uint8_t uart_frame_ready(void)
{
    return rx_frames;
}

uint8_t uart_frame(const uint8_t **frame)
{
    while (rx_frames) {
        uint8_t t = rx_tail, len = 0, over = 0, b;
        while ((b = rx_ring[t]) != 0) {
            if (len < UART_FRAME_MAX) {
                rx_frame[len++] = b;
            } else {
                over = 1;
            }
            t = (uint8_t)(t + 1u);
        }
        rx_tail = (uint8_t)(t + 1u); /* past the delimiter */
        {
            uint8_t s = SREG;
            cli();
            rx_frames--;
            SREG = s;
        }
        if (over) {
            *frame = rx_frame;
            return UART_OVERLONG;
        }
        if (len) {
            *frame = rx_frame;
            return len;
        }
        /* an empty frame: idle fill, skipped */
    }
    return 0;
}

void uart_frame_done(void)
{
}

uint8_t uart_put(const uint8_t *p, size_t len)
{
    uint8_t head = tx_head;
    uint8_t used = (uint8_t)(head - tx_tail);
    size_t i;
    if (len > (size_t)(TX_SIZE - 1u - used)) {
        return 0;
    }
    for (i = 0; i < len; i++) {
        tx_buf[head] = p[i];
        head = (uint8_t)(head + 1u);
    }
    tx_head = head;
    UCSR0B |= (uint8_t)(1 << UDRIE0);
    return 1;
}

uint16_t uart_rx_lost(void)
{
    uint16_t n;
    uint8_t s = SREG;
    cli();
    n = rx_lost;
    SREG = s;
    return n;
}
