/*
 * MIDAS-FPS pedal-board firmware (avr-libc, no Arduino core): up to 9 FSR voltage dividers on the
 * ADC, sampled by a Timer1 interrupt at a settable rate, streamed as MIDAS-FPS v1 lines (PROTOCOL.md).
 *
 * Timers: Timer0 runs free at F_CPU/64 and provides the microsecond clock (wraps at 2^32 us);
 * Timer1 in CTC mode ticks once per sample period. The tick handler only stamps the time and takes
 * the next sequence number; the main loop scans the ADC and formats the line. A tick that finds the
 * previous sample still unsent, or a line that does not fit the transmit buffer, is skipped: its
 * sequence number is never sent (the host sees a gap) and the banner's `skipped` counts it.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <stdint.h>

#include "fps_protocol.h"

#ifndef F_CPU
#error "F_CPU must be defined (the Makefile sets it)"
#endif
#ifndef FPS_BAUD
#define FPS_BAUD 500000UL
#endif
#ifndef FPS_FW_VERSION
#define FPS_FW_VERSION "1.0.0"
#endif
#ifndef FPS_DEFAULT_RATE_HZ
#define FPS_DEFAULT_RATE_HZ 250UL
#endif

#if defined(__AVR_ATmega2560__)
#define FPS_MCU "atmega2560"
#define FPS_ADC_INPUTS 16
#define FPS_RX_VECT USART0_RX_vect
#define FPS_UDRE_VECT USART0_UDRE_vect
#elif defined(__AVR_ATmega328P__)
#define FPS_MCU "atmega328p"
#define FPS_ADC_INPUTS 8
#define FPS_RX_VECT USART_RX_vect
#define FPS_UDRE_VECT USART_UDRE_vect
#else
#error "supported MCUs: atmega328p (Uno/Nano, up to 8 channels), atmega2560 (Mega, 9 channels)"
#endif

#ifndef FPS_CHANNELS
#define FPS_CHANNELS (FPS_ADC_INPUTS < FPS_MAX_CHANNELS ? FPS_ADC_INPUTS : FPS_MAX_CHANNELS)
#endif
#if FPS_CHANNELS < 1 || FPS_CHANNELS > FPS_MAX_CHANNELS || FPS_CHANNELS > FPS_ADC_INPUTS
#error "FPS_CHANNELS must be 1..9 and no more than the MCU's analog inputs"
#endif

#define TX_SIZE 256u /* power of two; indices wrap as uint8_t */
#define RX_SIZE 64u

static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;
static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail;

static volatile uint32_t timer0_overflows;
static volatile uint32_t next_seq;
static volatile uint32_t pending_seq, pending_us;
static volatile uint8_t sample_pending;
static volatile uint32_t skipped;
static volatile uint8_t running;
static uint32_t rate_hz = FPS_DEFAULT_RATE_HZ;

/* ---- time ------------------------------------------------------------------------------------ */

ISR(TIMER0_OVF_vect) { timer0_overflows++; }

/* Microseconds since boot (F_CPU/64 ticks); call with interrupts disabled. */
static uint32_t micros_locked(void)
{
    uint32_t overflows = timer0_overflows;
    uint8_t count = TCNT0;
    if ((TIFR0 & _BV(TOV0)) && count < 255) overflows++;
    return ((overflows << 8) + count) * (64UL * 1000000UL / F_CPU);
}

ISR(TIMER1_COMPA_vect)
{
    if (!running) return;
    if (sample_pending) {
        skipped++;
    } else {
        pending_us = micros_locked();
        pending_seq = next_seq;
        sample_pending = 1;
    }
    next_seq++;
}

/* Timer1 CTC period for `hz`: prescaler 64 down to 4 Hz, 1024 below. */
static void set_sample_timer(uint32_t hz)
{
    uint8_t sreg = SREG;
    cli();
    TCCR1A = 0;
    if (hz >= 4) {
        OCR1A = (uint16_t)(F_CPU / 64UL / hz - 1);
        TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10);
    } else {
        OCR1A = (uint16_t)(F_CPU / 1024UL / hz - 1);
        TCCR1B = _BV(WGM12) | _BV(CS12) | _BV(CS10);
    }
    TCNT1 = 0;
    TIMSK1 = _BV(OCIE1A);
    SREG = sreg;
}

/* ---- serial ---------------------------------------------------------------------------------- */

ISR(FPS_RX_VECT)
{
    uint8_t byte = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1u) % RX_SIZE);
    if (next != rx_tail) {
        rx_buf[rx_head] = byte;
        rx_head = next;
    }
}

ISR(FPS_UDRE_VECT)
{
    if (tx_head == tx_tail) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)(tx_tail + 1u);
}

static void uart_init(void)
{
    UCSR0A = _BV(U2X0);
    UBRR0 = (uint16_t)(F_CPU / 8UL / FPS_BAUD - 1UL);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

static uint8_t tx_free(void)
{
    return (uint8_t)(TX_SIZE - 1u - (uint8_t)(tx_head - tx_tail));
}

/* Queue a whole line or nothing; returns 0 when it did not fit. */
static uint8_t send_line(const char *line, size_t len)
{
    if (len > tx_free()) return 0;
    for (size_t i = 0; i < len; i++) {
        tx_buf[tx_head] = (uint8_t)line[i];
        tx_head = (uint8_t)(tx_head + 1u);
    }
    UCSR0B |= _BV(UDRIE0);
    return 1;
}

/* Replies must not be lost: wait for room (the transmitter drains at the baud rate). */
static void send_reply(const char *line, size_t len)
{
    while (!send_line(line, len)) {
    }
}

/* ---- ADC ------------------------------------------------------------------------------------- */

static void adc_init(void)
{
    ADMUX = _BV(REFS0);                                /* AVcc reference */
    ADCSRA = _BV(ADEN) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0); /* F_CPU / 128 */
}

static uint16_t adc_read(uint8_t input)
{
    ADMUX = (uint8_t)(_BV(REFS0) | (input & 0x07u));
#if defined(ADCSRB) && defined(MUX5)
    ADCSRB = (uint8_t)((input & 0x08u) ? _BV(MUX5) : 0);
#endif
    ADCSRA |= _BV(ADSC);
    while (ADCSRA & _BV(ADSC)) {
    }
    return ADC;
}

/* ---- protocol -------------------------------------------------------------------------------- */

static void send_banner(void)
{
    char line[FPS_LINE_MAX];
    uint8_t sreg = SREG;
    cli();
    fps_banner banner = {FPS_FW_VERSION, FPS_MCU, FPS_CHANNELS, rate_hz, FPS_BAUD, running, skipped};
    SREG = sreg;
    send_reply(line, fps_format_banner(line, &banner));
}

static void set_running(uint8_t on)
{
    cli();
    running = on;
    sample_pending = 0;
    TCNT1 = 0;
    sei();
}

static void execute(const fps_command *cmd)
{
    char line[FPS_LINE_MAX];
    if (cmd->kind == FPS_CMD_ID) {
        send_banner();
        return;
    }
    if (cmd->kind == FPS_CMD_RATE && !fps_rate_fits(cmd->arg, FPS_CHANNELS, FPS_BAUD)) {
        send_reply(line, fps_format_error(line, FPS_ERR_RANGE));
        return;
    }
    if (cmd->kind == FPS_CMD_ERROR) {
        send_reply(line, fps_format_error(line, cmd->error));
        return;
    }
    if (cmd->kind == FPS_CMD_RATE) {
        rate_hz = cmd->arg;
        set_sample_timer(rate_hz);
    }
    if (cmd->kind == FPS_CMD_STOP) set_running(0); /* no sample after OK STOP */
    send_reply(line, fps_format_ok(line, cmd->kind, rate_hz));
    if (cmd->kind == FPS_CMD_START) set_running(1); /* no sample before OK START */
}

static void poll_commands(fps_line_buffer *lb)
{
    fps_command cmd;
    while (rx_tail != rx_head) {
        char byte = (char)rx_buf[rx_tail];
        rx_tail = (uint8_t)((rx_tail + 1u) % RX_SIZE);
        if (fps_line_feed(lb, byte, &cmd) && cmd.kind != FPS_CMD_NONE) execute(&cmd);
    }
}

static void send_pending_sample(void)
{
    uint16_t adc[FPS_CHANNELS];
    char line[FPS_LINE_MAX];
    for (uint8_t c = 0; c < FPS_CHANNELS; c++) adc[c] = adc_read(c);
    cli();
    uint32_t seq = pending_seq, t_us = pending_us;
    sei();
    size_t len = fps_format_sample(line, seq, t_us, adc, FPS_CHANNELS);
    cli();
    if (!send_line(line, len)) skipped++;
    sample_pending = 0;
    sei();
}

int main(void)
{
    fps_line_buffer commands = {{0}, 0, 0};
    TCCR0A = 0;
    TCCR0B = _BV(CS01) | _BV(CS00); /* F_CPU / 64 */
    TIMSK0 = _BV(TOIE0);
    uart_init();
    adc_init();
    set_sample_timer(rate_hz);
    sei();
    send_banner();
    for (;;) {
        poll_commands(&commands);
        if (sample_pending) send_pending_sample();
    }
}
