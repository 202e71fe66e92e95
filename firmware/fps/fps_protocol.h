/*
 * MIDAS-FPS line protocol, version 1: formatting, checksums and command parsing.
 *
 * Portable C99 with no hardware access, so the same file runs in the AVR firmware (main.c) and in
 * the host-side harness (host_harness.c) that the Python test suite compiles with gcc and compares
 * byte for byte against midas_cli/devices/fps/protocol.py. The grammar is in PROTOCOL.md.
 */
#ifndef FPS_PROTOCOL_H
#define FPS_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#define FPS_PROTO_VERSION 1
#define FPS_MAX_CHANNELS 9
#define FPS_ADC_MAX 1023u
#define FPS_MAX_RATE_HZ 1000u
#define FPS_CMD_MAX 31            /* longest accepted command line, without the LF */
#define FPS_LINE_MAX 96           /* longest line the board sends, LF included */
#define FPS_ADC_US_PER_CHANNEL 104u /* 13 ADC clocks at 16 MHz / 128 */

/* Length in bytes (LF included) of a sample line with `channels` ADC values. */
#define FPS_SAMPLE_LINE_LEN(channels) (23u + 3u * (channels))

typedef enum {
    FPS_CMD_NONE = 0,  /* empty line: ignored, no reply */
    FPS_CMD_ID,
    FPS_CMD_START,
    FPS_CMD_STOP,
    FPS_CMD_RATE,
    FPS_CMD_ERROR      /* see fps_command.error */
} fps_command_kind;

typedef enum {
    FPS_ERR_NONE = 0,
    FPS_ERR_UNKNOWN,
    FPS_ERR_ARG,
    FPS_ERR_CRC,
    FPS_ERR_LONG,
    FPS_ERR_RANGE
} fps_error_code;

typedef struct {
    fps_command_kind kind;
    fps_error_code error;
    uint32_t arg;      /* RATE: the requested rate in Hz */
} fps_command;

typedef struct {
    const char *fw;    /* firmware version, e.g. "1.0.0" */
    const char *mcu;   /* e.g. "atmega328p" */
    uint8_t channels;
    uint32_t rate_hz;
    uint32_t baud;
    uint8_t running;
    uint32_t skipped;  /* samples not sent since boot (TX buffer full or sampling overrun) */
} fps_banner;

/* CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR. */
uint16_t fps_crc16(const char *data, size_t len);

/* Each formatter writes one complete line (body, '*', 4 hex CRC digits, LF) into `out`, which must
 * hold FPS_LINE_MAX bytes, and returns its length. No NUL terminator is written. */
size_t fps_format_sample(char *out, uint32_t seq, uint32_t t_us, const uint16_t *adc, uint8_t channels);
size_t fps_format_banner(char *out, const fps_banner *banner);
size_t fps_format_ok(char *out, fps_command_kind kind, uint32_t rate_hz);
size_t fps_format_error(char *out, fps_error_code code);

/* Parse one received command line (without its LF; a trailing CR is ignored). */
fps_command fps_parse_command(const char *line, size_t len);

/* 1 if `rate_hz` is allowed for `channels` at `baud`: 1..FPS_MAX_RATE_HZ, the sample lines fit the
 * wire (10 bits per byte) and the ADC scan takes at most 80 % of the sample period. */
uint8_t fps_rate_fits(uint32_t rate_hz, uint8_t channels, uint32_t baud);

/* Accumulates received bytes into command lines. */
typedef struct {
    char buf[FPS_CMD_MAX + 1];
    uint8_t len;
    uint8_t overflow;
} fps_line_buffer;

/* Feed one byte; returns 1 and fills *command when a line (LF) completes, else 0. */
uint8_t fps_line_feed(fps_line_buffer *lb, char byte, fps_command *command);

#endif
