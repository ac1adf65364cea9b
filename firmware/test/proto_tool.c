/*
 * Host-side driver of the firmware's plain-C logic, for cross-checks from Python
 * (test/test_firmware.py). Reads commands from stdin, one per line:
 *   parse <hex>                 feed bytes to a fresh parser; prints "F <type> <seq> <payload>"
 *                               per frame, then "S <frames_ok> <crc_errors> <bytes_dropped>"
 *   rx <now_ms> <hex>           feed bytes to the board
 *   tick <now_ms> <raw0> <raw1> run one control tick; prints
 *                               "O <status> <code0> <code1> <user0> <user1> <out0> <out1>"
 *   crc <hex>                   prints "C <crc>"
 * Every frame the board writes is printed as "W <hex>".
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "board.h"

static void print_hex(const uint8_t *d, size_t n)
{
    if (n == 0) {
        fputs("-", stdout);
    }
    for (size_t i = 0; i < n; ++i) {
        printf("%02X", d[i]);
    }
}

static void on_write(const uint8_t *data, size_t len, void *ctx)
{
    (void)ctx;
    fputs("W ", stdout);
    print_hex(data, len);
    fputs("\n", stdout);
}

static size_t parse_hex(const char *s, uint8_t *out, size_t cap)
{
    size_t n = 0;
    if (strcmp(s, "-") == 0) {
        return 0;
    }
    while (s[0] && s[1] && n < cap) {
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1) {
            break;
        }
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static char line[1 << 21];
static uint8_t bytes[1 << 20];

int main(void)
{
    asgp_board_t board;
    asgp_board_init(&board, on_write, NULL);
    while (fgets(line, sizeof(line), stdin)) {
        char cmd[16];
        char *rest;
        if (sscanf(line, "%15s", cmd) != 1) {
            continue;
        }
        rest = line + strlen(cmd);
        while (*rest == ' ') {
            rest++;
        }
        rest[strcspn(rest, "\r\n")] = 0;
        if (strcmp(cmd, "parse") == 0) {
            asgp_parser_t p;
            asgp_frame_t f;
            asgp_parser_init(&p);
            size_t n = parse_hex(rest, bytes, sizeof(bytes));
            for (size_t i = 0; i < n; ++i) {
                int got = asgp_parser_feed(&p, bytes[i], &f);
                while (got) {
                    printf("F %u %u ", f.type, f.seq);
                    print_hex(f.payload, f.len);
                    fputs("\n", stdout);
                    got = asgp_parser_next(&p, &f);
                }
            }
            printf("S %u %u %u\n", p.frames_ok, p.crc_errors, p.bytes_dropped);
        } else if (strcmp(cmd, "crc") == 0) {
            size_t n = parse_hex(rest, bytes, sizeof(bytes));
            printf("C %04X\n", asgp_crc16(bytes, n));
        } else if (strcmp(cmd, "rx") == 0) {
            unsigned long now;
            char hex[4096];
            if (sscanf(rest, "%lu %4095s", &now, hex) != 2) {
                return 2;
            }
            size_t n = parse_hex(hex, bytes, sizeof(bytes));
            for (size_t i = 0; i < n; ++i) {
                asgp_board_rx(&board, bytes[i], (uint32_t)now);
            }
        } else if (strcmp(cmd, "tick") == 0) {
            unsigned long now;
            int r0, r1;
            if (sscanf(rest, "%lu %d %d", &now, &r0, &r1) != 3) {
                return 2;
            }
            int16_t raw[2] = {(int16_t)r0, (int16_t)r1};
            const asgp_output_t *o = asgp_board_tick(&board, raw, (uint32_t)now);
            printf("O %u %u %u %d %d %d %d\n", o->status, o->out_code[0], o->out_code[1],
                   o->user_pm[0], o->user_pm[1], o->out_pm[0], o->out_pm[1]);
        } else {
            fprintf(stderr, "unknown command %s\n", cmd);
            return 2;
        }
        fflush(stdout);
    }
    return 0;
}
