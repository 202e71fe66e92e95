/*
 * Host-side driver of fps_protocol.c for the test suite (tests/devices/test_fps_firmware.py): reads one
 * request per stdin line and writes the protocol's output, so every formatter and the command parser
 * can be compared byte for byte with midas_cli/devices/fps/protocol.py.
 *
 *   sample SEQ T_US A1 .. An      -> the sample line
 *   banner FW MCU CH RATE BAUD RUN SKIPPED -> the banner line
 *   ok START|STOP|RATE HZ         -> the reply line
 *   err CODE                      -> the error line (CODE as a number, 1..5)
 *   fits RATE CH BAUD             -> "1" or "0" and LF
 *   cmd HEX                       -> the parsed command of the bytes HEX (hex-encoded, may be empty):
 *                                    "NONE", "ID", "START", "STOP", "RATE n" or "ERR code", and LF
 *   feed HEX                      -> the same, for each line completed by feeding bytes HEX one by one
 * Numbers are decimal.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fps_protocol.h"

static void emit(const char *line, size_t len) { fwrite(line, 1, len, stdout); }

static size_t unhex(const char *text, char *out, size_t cap)
{
    size_t n = 0;
    for (; text[0] && text[1] && n < cap; text += 2) {
        char pair[3] = {text[0], text[1], 0};
        out[n++] = (char)strtoul(pair, NULL, 16);
    }
    return n;
}

static void print_command(fps_command cmd)
{
    static const char *const KINDS[] = {"NONE", "ID", "START", "STOP", "RATE", "ERR"};
    if (cmd.kind == FPS_CMD_RATE) printf("RATE %lu\n", (unsigned long)cmd.arg);
    else if (cmd.kind == FPS_CMD_ERROR) printf("ERR %d\n", (int)cmd.error);
    else printf("%s\n", KINDS[cmd.kind]);
}

static void do_sample(char *args)
{
    uint16_t adc[FPS_MAX_CHANNELS];
    char line[FPS_LINE_MAX];
    unsigned long seq = strtoul(strtok(args, " "), NULL, 10);
    unsigned long t_us = strtoul(strtok(NULL, " "), NULL, 10);
    uint8_t n = 0;
    for (char *tok = strtok(NULL, " "); tok && n < FPS_MAX_CHANNELS; tok = strtok(NULL, " ")) {
        adc[n++] = (uint16_t)strtoul(tok, NULL, 10);
    }
    emit(line, fps_format_sample(line, (uint32_t)seq, (uint32_t)t_us, adc, n));
}

static void do_banner(char *args)
{
    char line[FPS_LINE_MAX];
    fps_banner b;
    b.fw = strtok(args, " ");
    b.mcu = strtok(NULL, " ");
    b.channels = (uint8_t)atoi(strtok(NULL, " "));
    b.rate_hz = (uint32_t)strtoul(strtok(NULL, " "), NULL, 10);
    b.baud = (uint32_t)strtoul(strtok(NULL, " "), NULL, 10);
    b.running = (uint8_t)atoi(strtok(NULL, " "));
    b.skipped = (uint32_t)strtoul(strtok(NULL, " "), NULL, 10);
    emit(line, fps_format_banner(line, &b));
}

static void do_ok(char *args)
{
    char line[FPS_LINE_MAX];
    char *what = strtok(args, " ");
    char *hz = strtok(NULL, " ");
    fps_command_kind kind = strcmp(what, "START") == 0 ? FPS_CMD_START
                          : strcmp(what, "STOP") == 0 ? FPS_CMD_STOP : FPS_CMD_RATE;
    emit(line, fps_format_ok(line, kind, hz ? (uint32_t)strtoul(hz, NULL, 10) : 0));
}

static void do_feed(const char *hex)
{
    char bytes[512];
    size_t n = unhex(hex, bytes, sizeof bytes);
    fps_line_buffer lb = {{0}, 0, 0};
    fps_command cmd;
    for (size_t i = 0; i < n; i++) {
        if (fps_line_feed(&lb, bytes[i], &cmd)) print_command(cmd);
    }
}

int main(void)
{
    static char request[4096];
    while (fgets(request, sizeof request, stdin)) {
        request[strcspn(request, "\n")] = 0;
        char *space = strchr(request, ' ');
        char *args = space ? space + 1 : request + strlen(request);
        if (space) *space = 0;
        char line[FPS_LINE_MAX];
        if (strcmp(request, "sample") == 0) do_sample(args);
        else if (strcmp(request, "banner") == 0) do_banner(args);
        else if (strcmp(request, "ok") == 0) do_ok(args);
        else if (strcmp(request, "err") == 0) emit(line, fps_format_error(line, (fps_error_code)atoi(args)));
        else if (strcmp(request, "fits") == 0) {
            unsigned long rate = strtoul(strtok(args, " "), NULL, 10);
            int ch = atoi(strtok(NULL, " "));
            unsigned long baud = strtoul(strtok(NULL, " "), NULL, 10);
            printf("%d\n", fps_rate_fits((uint32_t)rate, (uint8_t)ch, (uint32_t)baud));
        } else if (strcmp(request, "cmd") == 0) {
            char bytes[512];
            print_command(fps_parse_command(bytes, unhex(args, bytes, sizeof bytes)));
        } else if (strcmp(request, "feed") == 0) do_feed(args);
        else {
            fprintf(stderr, "unknown request %s\n", request);
            return 2;
        }
        fflush(stdout);
    }
    return 0;
}
