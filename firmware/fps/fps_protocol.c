/* MIDAS-FPS line protocol v1 (see fps_protocol.h and PROTOCOL.md). No stdio, no heap: fits an AVR. */
#include "fps_protocol.h"

static const char HEX[] = "0123456789ABCDEF";

uint16_t fps_crc16(const char *data, size_t len)
{
    uint16_t crc = 0xFFFFu;
    for (size_t i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint8_t)data[i]) << 8;
        for (uint8_t bit = 0; bit < 8; bit++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

static size_t put_hex(char *out, uint32_t value, uint8_t digits)
{
    for (uint8_t i = 0; i < digits; i++) {
        out[digits - 1 - i] = HEX[value & 0xFu];
        value >>= 4;
    }
    return digits;
}

static size_t put_dec(char *out, uint32_t value)
{
    char tmp[10];
    size_t n = 0;
    do {
        tmp[n++] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value);
    for (size_t i = 0; i < n; i++) {
        out[i] = tmp[n - 1 - i];
    }
    return n;
}

static size_t put_str(char *out, const char *text)
{
    size_t n = 0;
    while (text[n] && n < 24) {
        out[n] = text[n];
        n++;
    }
    return n;
}

/* Append "*CCCC\n" after a body of `len` bytes; return the full line length. */
static size_t finish_line(char *out, size_t len)
{
    uint16_t crc = fps_crc16(out, len);
    out[len++] = '*';
    len += put_hex(out + len, crc, 4);
    out[len++] = '\n';
    return len;
}

size_t fps_format_sample(char *out, uint32_t seq, uint32_t t_us, const uint16_t *adc, uint8_t channels)
{
    size_t len = 0;
    out[len++] = 'D';
    len += put_hex(out + len, seq, 8);
    len += put_hex(out + len, t_us, 8);
    for (uint8_t c = 0; c < channels && c < FPS_MAX_CHANNELS; c++) {
        len += put_hex(out + len, adc[c] > FPS_ADC_MAX ? FPS_ADC_MAX : adc[c], 3);
    }
    return finish_line(out, len);
}

static size_t put_key_dec(char *out, const char *key, uint32_t value)
{
    size_t len = put_str(out, key);
    return len + put_dec(out + len, value);
}

size_t fps_format_banner(char *out, const fps_banner *b)
{
    size_t len = put_str(out, "#MIDAS-FPS");
    len += put_key_dec(out + len, " proto=", FPS_PROTO_VERSION);
    len += put_str(out + len, " fw=");
    len += put_str(out + len, b->fw);
    len += put_str(out + len, " mcu=");
    len += put_str(out + len, b->mcu);
    len += put_key_dec(out + len, " ch=", b->channels);
    len += put_key_dec(out + len, " rate=", b->rate_hz);
    len += put_key_dec(out + len, " baud=", b->baud);
    len += put_key_dec(out + len, " run=", b->running);
    len += put_key_dec(out + len, " skipped=", b->skipped);
    return finish_line(out, len);
}

size_t fps_format_ok(char *out, fps_command_kind kind, uint32_t rate_hz)
{
    size_t len = put_str(out, "OK ");
    if (kind == FPS_CMD_START) {
        len += put_str(out + len, "START");
    } else if (kind == FPS_CMD_STOP) {
        len += put_str(out + len, "STOP");
    } else {
        len += put_str(out + len, "RATE ");
        len += put_dec(out + len, rate_hz);
    }
    return finish_line(out, len);
}

size_t fps_format_error(char *out, fps_error_code code)
{
    static const char *const NAMES[] = {"NONE", "UNKNOWN", "ARG", "CRC", "LONG", "RANGE"};
    size_t len = put_str(out, "ERR ");
    len += put_str(out + len, NAMES[code <= FPS_ERR_RANGE ? code : FPS_ERR_UNKNOWN]);
    return finish_line(out, len);
}

static int hex_value(char c)
{
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}

static uint8_t same(const char *a, size_t len, const char *word)
{
    size_t i = 0;
    for (; i < len; i++) {
        if (word[i] != a[i]) return 0;
    }
    return word[i] == '\0';
}

static fps_command error_command(fps_error_code code)
{
    fps_command cmd = {FPS_CMD_ERROR, code, 0};
    return cmd;
}

/* "RATE " followed by 1..5 decimal digits and nothing else. */
static fps_command parse_rate(const char *arg, size_t len)
{
    fps_command cmd = {FPS_CMD_RATE, FPS_ERR_NONE, 0};
    if (len < 1 || len > 5) return error_command(FPS_ERR_ARG);
    for (size_t i = 0; i < len; i++) {
        if (arg[i] < '0' || arg[i] > '9') return error_command(FPS_ERR_ARG);
        cmd.arg = cmd.arg * 10u + (uint32_t)(arg[i] - '0');
    }
    return cmd;
}

/* Strip and check an optional "*CCCC" suffix; returns the body length or -1 on a bad checksum. */
static long checked_body(const char *line, size_t len)
{
    size_t star = len;
    while (star > 0 && line[star - 1] != '*') star--;
    if (star == 0) return (long)len;
    star--; /* index of the last '*' */
    if (len - star != 5) return -1;
    uint16_t want = 0;
    for (size_t i = star + 1; i < len; i++) {
        int v = hex_value(line[i]);
        if (v < 0) return -1;
        want = (uint16_t)((want << 4) | (uint16_t)v);
    }
    return fps_crc16(line, star) == want ? (long)star : -1;
}

fps_command fps_parse_command(const char *line, size_t len)
{
    fps_command cmd = {FPS_CMD_NONE, FPS_ERR_NONE, 0};
    if (len > 0 && line[len - 1] == '\r') len--;
    if (len == 0) return cmd;
    if (len > FPS_CMD_MAX) return error_command(FPS_ERR_LONG);
    long body = checked_body(line, len);
    if (body < 0) return error_command(FPS_ERR_CRC);
    size_t n = (size_t)body;
    if (same(line, n, "ID")) cmd.kind = FPS_CMD_ID;
    else if (same(line, n, "START")) cmd.kind = FPS_CMD_START;
    else if (same(line, n, "STOP")) cmd.kind = FPS_CMD_STOP;
    else if (n >= 4 && same(line, 4, "RATE") && (n == 4 || line[4] == ' ')) {
        return n == 4 ? error_command(FPS_ERR_ARG) : parse_rate(line + 5, n - 5);
    } else return error_command(FPS_ERR_UNKNOWN);
    return cmd;
}

uint8_t fps_rate_fits(uint32_t rate_hz, uint8_t channels, uint32_t baud)
{
    if (rate_hz < 1 || rate_hz > FPS_MAX_RATE_HZ || channels < 1 || channels > FPS_MAX_CHANNELS) return 0;
    if ((uint64_t)rate_hz * FPS_SAMPLE_LINE_LEN(channels) * 10u > baud) return 0;
    return (uint64_t)rate_hz * channels * FPS_ADC_US_PER_CHANNEL <= 800000u;
}

uint8_t fps_line_feed(fps_line_buffer *lb, char byte, fps_command *command)
{
    if (byte != '\n') {
        if (lb->len < FPS_CMD_MAX + 1) lb->buf[lb->len++] = byte;
        else lb->overflow = 1;
        return 0;
    }
    *command = lb->overflow ? error_command(FPS_ERR_LONG) : fps_parse_command(lb->buf, lb->len);
    lb->len = 0;
    lb->overflow = 0;
    return 1;
}
