/*
 * Host unit test of the firmware's plain-C logic (protocol.c, safety.c, board.c), built
 * with gcc by `make check` and by test/test_firmware.py. Usage: test_host vectors.txt
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "board.h"
#include "config.h"

static int failures = 0;
static int checks = 0;

#define CHECK(cond)                                                                         \
    do {                                                                                    \
        checks++;                                                                           \
        if (!(cond)) {                                                                      \
            failures++;                                                                     \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);      \
        }                                                                                   \
    } while (0)

static size_t unhex(const char *s, uint8_t *out)
{
    size_t n = 0;
    if (strcmp(s, "-") == 0) {
        return 0;
    }
    while (s[0] && s[1]) {
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1) {
            break;
        }
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

/* -- shared vectors --------------------------------------------------------------------- */

static void test_vectors(const char *path)
{
    FILE *f = fopen(path, "r");
    char line[512];
    int n_crc = 0, n_frame = 0;
    if (!f) {
        fprintf(stderr, "cannot open %s\n", path);
        failures++;
        return;
    }
    while (fgets(line, sizeof(line), f)) {
        char kind[16], a[256], b[256], c[256], d[256];
        uint8_t data[256], frame[ASGP_MAX_FRAME], expected[256];
        if (line[0] == '#' || sscanf(line, "%15s", kind) != 1) {
            continue;
        }
        if (strcmp(kind, "crc") == 0 && sscanf(line, "%*s %255s %255s", a, b) == 2) {
            size_t n = unhex(a, data);
            CHECK(asgp_crc16(data, n) == (uint16_t)strtoul(b, NULL, 16));
            n_crc++;
        } else if (strcmp(kind, "frame") == 0 &&
                   sscanf(line, "%*s %255s %255s %255s %255s", a, b, c, d) == 4) {
            uint8_t type = (uint8_t)strtoul(a, NULL, 16);
            uint8_t seq = (uint8_t)strtoul(b, NULL, 10);
            size_t plen = unhex(c, data);
            size_t flen = unhex(d, expected);
            size_t got = asgp_encode(frame, type, seq, data, (uint8_t)plen);
            CHECK(got == flen && memcmp(frame, expected, flen) == 0);
            /* and the parser takes it back */
            asgp_parser_t p;
            asgp_frame_t out;
            int frames = 0;
            asgp_parser_init(&p);
            for (size_t i = 0; i < flen; ++i) {
                frames += asgp_parser_feed(&p, expected[i], &out);
            }
            CHECK(frames == 1 && out.type == type && out.seq == seq && out.len == plen &&
                  memcmp(out.payload, data, plen) == 0);
            n_frame++;
        }
    }
    fclose(f);
    CHECK(n_crc >= 3 && n_frame >= 7);
}

/* -- parser ----------------------------------------------------------------------------- */

static int feed_all(asgp_parser_t *p, const uint8_t *d, size_t n, asgp_frame_t *frames, int cap)
{
    int k = 0;
    for (size_t i = 0; i < n; ++i) {
        asgp_frame_t f;
        int got = asgp_parser_feed(p, d[i], &f);
        while (got) {
            if (k < cap) {
                frames[k] = f;
            }
            k++;
            got = asgp_parser_next(p, &f);
        }
    }
    return k;
}

static void test_parser_resync(void)
{
    uint8_t good[ASGP_MAX_FRAME], stream[256];
    uint8_t pl[4] = {1, 2, 3, 4};
    size_t gl = asgp_encode(good, ASGP_MSG_OVERRIDE, 5, pl, 4);
    asgp_parser_t p;
    asgp_frame_t fr[8];
    size_t n = 0;

    /* garbage with fake sync markers and an impossible length, then a frame */
    const uint8_t junk[] = {0x00, 0xA5, 0x13, 0xA5, 0x5A, 0xFF, 0xA5, 0x5A, 0x03, 0x01};
    memcpy(stream, junk, sizeof(junk));
    n = sizeof(junk);
    memcpy(stream + n, good, gl);
    n += gl;
    asgp_parser_init(&p);
    CHECK(feed_all(&p, stream, n, fr, 8) == 1 && fr[0].seq == 5);

    /* a cut frame (first 6 bytes) directly followed by a whole one */
    memcpy(stream, good, 6);
    memcpy(stream + 6, good, gl);
    asgp_parser_init(&p);
    CHECK(feed_all(&p, stream, 6 + gl, fr, 8) == 1);
    CHECK(p.crc_errors == 1);

    /* a flipped bit is never accepted */
    for (size_t bit = 0; bit < gl * 8; ++bit) {
        memcpy(stream, good, gl);
        stream[bit / 8] ^= (uint8_t)(1u << (bit % 8));
        asgp_parser_init(&p);
        int k = feed_all(&p, stream, gl, fr, 8);
        CHECK(k == 0);
    }

    /* two frames hidden inside a corrupt long frame are both delivered, in order */
    uint8_t small[ASGP_MAX_FRAME];
    size_t sl = asgp_encode(small, ASGP_MSG_MODE, 1, pl, 1);
    n = 0;
    stream[n++] = ASGP_SYNC0;
    stream[n++] = ASGP_SYNC1;
    stream[n++] = 20; /* claims 20 payload bytes */
    stream[n++] = 0x01;
    stream[n++] = 0x00;
    memcpy(stream + n, small, sl);
    n += sl;
    small[4] = 2; /* second one with seq 2 */
    asgp_encode(small, ASGP_MSG_MODE, 2, pl, 1);
    memcpy(stream + n, small, sl);
    n += sl;
    while (n < 27) {
        stream[n++] = 0x11;
    }
    asgp_parser_init(&p);
    int k = feed_all(&p, stream, n, fr, 8);
    CHECK(k == 2 && fr[0].seq == 1 && fr[1].seq == 2);
}

/* -- safety ----------------------------------------------------------------------------- */

static void test_calibration(void)
{
    asgp_axis_cal_t cal[2];
    uint8_t clamped = 0;
    asgp_default_calibration(cal);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL) == 0);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL + ASGP_ADC_DEADBAND) == 0);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL - ASGP_ADC_DEADBAND) == 0);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL + ASGP_ADC_DEADBAND + 1) > 0);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL + ASGP_ADC_SPAN) == 1000);
    CHECK(asgp_adc_to_permille(&cal[0], ASGP_ADC_NEUTRAL - ASGP_ADC_SPAN) == -1000);
    CHECK(asgp_adc_to_permille(&cal[0], 1023) == 1000);
    CHECK(asgp_permille_to_dac(&cal[0], 0, &clamped) == ASGP_DAC_NEUTRAL && !clamped);
    CHECK(asgp_permille_to_dac(&cal[0], 1000, &clamped) == ASGP_DAC_NEUTRAL + ASGP_DAC_SPAN);
    CHECK(asgp_permille_to_dac(&cal[0], -1000, &clamped) == ASGP_DAC_NEUTRAL - ASGP_DAC_SPAN);
    CHECK(!clamped);
    /* a tighter calibrated range clamps, and says so */
    cal[0].limit_neg = 500;
    CHECK(asgp_permille_to_dac(&cal[0], -800, &clamped) ==
          ASGP_DAC_NEUTRAL - 410 && clamped); /* -409.5 rounds away from zero */
    clamped = 0;
    cal[0].limit_neg = 1000;
    cal[0].dac_max = 2500;
    CHECK(asgp_permille_to_dac(&cal[0], 1000, &clamped) == 2500 && clamped);
}

static void test_watchdog_and_neutral(void)
{
    asgp_safety_t s;
    asgp_axis_cal_t cal[2];
    asgp_output_t o;
    const int16_t pushed[2] = {ASGP_ADC_NEUTRAL + ASGP_ADC_SPAN / 2, ASGP_ADC_NEUTRAL};
    const int16_t neutral[2] = {ASGP_ADC_NEUTRAL + 3, ASGP_ADC_NEUTRAL - 5};
    asgp_default_calibration(cal);
    asgp_safety_init(&s);

    /* passthrough */
    asgp_safety_step(&s, cal, pushed, 0, &o);
    CHECK(o.out_pm[0] == o.user_pm[0] && o.out_pm[0] > 400 && o.status == 0);

    /* override refused outside override mode, and out of range */
    CHECK(asgp_safety_set_override(&s, 300, 0, 0) == ASGP_ERR_NOT_IN_OVERRIDE);
    CHECK(asgp_safety_set_mode(&s, 7, 0) == ASGP_ERR_BAD_MODE);
    CHECK(asgp_safety_set_mode(&s, ASGP_MODE_OVERRIDE, 0) == 0);
    CHECK(asgp_safety_set_override(&s, 1001, 0, 0) == ASGP_ERR_OVERRIDE_RANGE);
    CHECK(asgp_safety_set_override(&s, 0, -1001, 0) == ASGP_ERR_OVERRIDE_RANGE);
    asgp_safety_step(&s, cal, pushed, 10, &o);
    CHECK((o.status & ASGP_ST_WATCHDOG) && o.out_pm[0] == o.user_pm[0]);

    /* a fresh override drives the output until ASGP_WATCHDOG_MS after it arrived */
    CHECK(asgp_safety_set_override(&s, 300, -200, 1000) == 0);
    asgp_safety_step(&s, cal, pushed, 1000, &o);
    CHECK(o.out_pm[0] == 300 && o.out_pm[1] == -200 && (o.status & ASGP_ST_OVERRIDE_ACTIVE));
    asgp_safety_step(&s, cal, pushed, 1000 + ASGP_WATCHDOG_MS - 1, &o);
    CHECK(o.out_pm[0] == 300 && !(o.status & ASGP_ST_WATCHDOG));
    asgp_safety_step(&s, cal, pushed, 1000 + ASGP_WATCHDOG_MS, &o);
    CHECK(o.out_pm[0] == o.user_pm[0] && (o.status & ASGP_ST_WATCHDOG) &&
          !(o.status & ASGP_ST_OVERRIDE_ACTIVE));

    /* the user at neutral always gives neutral, even with a fresh override */
    CHECK(asgp_safety_set_override(&s, 800, 800, 2000) == 0);
    asgp_safety_step(&s, cal, neutral, 2000, &o);
    CHECK(o.out_pm[0] == 0 && o.out_pm[1] == 0 && (o.status & ASGP_ST_NEUTRAL_STOP));
    CHECK(o.out_code[0] == ASGP_DAC_NEUTRAL && o.out_code[1] == ASGP_DAC_NEUTRAL);
    /* and the override resumes when the user pushes again, while still fresh */
    asgp_safety_step(&s, cal, pushed, 2050, &o);
    CHECK(o.out_pm[0] == 800 && o.out_pm[1] == 800);

    /* ADC fault -> neutral */
    const int16_t broken[2] = {1023, ASGP_ADC_NEUTRAL};
    asgp_safety_step(&s, cal, broken, 2060, &o);
    CHECK((o.status & ASGP_ST_ADC_FAULT) && o.out_code[0] == ASGP_DAC_NEUTRAL);

    /* watchdog across the 32-bit millis() wrap */
    CHECK(asgp_safety_set_override(&s, 100, 0, 0xFFFFFFF0u) == 0);
    asgp_safety_step(&s, cal, pushed, 0x00000050u, &o);
    CHECK(o.out_pm[0] == 100);
    asgp_safety_step(&s, cal, pushed, 0xFFFFFFF0u + ASGP_WATCHDOG_MS, &o);
    CHECK(o.out_pm[0] == o.user_pm[0]);

    /* a mode change drops the override */
    CHECK(asgp_safety_set_override(&s, 100, 0, 5000) == 0);
    CHECK(asgp_safety_set_mode(&s, ASGP_MODE_PASSTHROUGH, 5000) == 0);
    CHECK(asgp_safety_set_mode(&s, ASGP_MODE_OVERRIDE, 5000) == 0);
    asgp_safety_step(&s, cal, pushed, 5001, &o);
    CHECK(o.out_pm[0] == o.user_pm[0]);

    /* host silent for ASGP_HOST_TIMEOUT_MS -> mode passthrough */
    asgp_safety_host_alive(&s, 6000);
    asgp_safety_step(&s, cal, pushed, 6000 + ASGP_HOST_TIMEOUT_MS, &o);
    CHECK(s.mode == ASGP_MODE_PASSTHROUGH && (o.status & ASGP_ST_HOST_LOST));
}

/* -- board ------------------------------------------------------------------------------ */

static uint8_t written[4096];
static size_t n_written = 0;

static void capture(const uint8_t *data, size_t len, void *ctx)
{
    (void)ctx;
    if (n_written + len <= sizeof(written)) {
        memcpy(written + n_written, data, len);
        n_written += len;
    }
}

static void send_to(asgp_board_t *b, uint8_t type, uint8_t seq, const uint8_t *pl,
                    uint8_t len, uint32_t now)
{
    uint8_t f[ASGP_MAX_FRAME];
    size_t n = asgp_encode(f, type, seq, pl, len);
    for (size_t i = 0; i < n; ++i) {
        asgp_board_rx(b, f[i], now);
    }
}

static void test_board(void)
{
    asgp_board_t b;
    asgp_parser_t p;
    asgp_frame_t fr[64];
    const int16_t pushed[2] = {700, 300};
    const int16_t neutral_raw[2] = {512, 512};
    uint8_t pl[4];
    asgp_board_init(&b, capture, NULL);
    asgp_parser_init(&p);

    pl[0] = ASGP_PROTOCOL_VERSION;
    send_to(&b, ASGP_MSG_HELLO, 0, pl, 1, 0);
    send_to(&b, ASGP_MSG_HELLO, 1, pl, 1, 0); /* a second HELLO in the same tick */
    int k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 0); /* VERSION waits for the tick: a HELLO flood cannot fill the UART */
    asgp_board_tick(&b, neutral_raw, 5);
    k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 2 && fr[0].type == ASGP_MSG_SAMPLE && fr[1].type == ASGP_MSG_VERSION &&
          fr[1].len == ASGP_LEN_VERSION && fr[1].payload[0] == ASGP_PROTOCOL_VERSION &&
          asgp_get_u16(fr[1].payload + 6) == ASGP_WATCHDOG_MS); /* one VERSION a tick */

    /* override reaches the output; samples report it */
    n_written = 0;
    pl[0] = ASGP_MODE_OVERRIDE;
    send_to(&b, ASGP_MSG_MODE, 1, pl, 1, 10);
    asgp_put_u16(pl, (uint16_t)(int16_t)-400);
    asgp_put_u16(pl + 2, 250);
    send_to(&b, ASGP_MSG_OVERRIDE, 2, pl, 4, 10);
    const asgp_output_t *o = asgp_board_tick(&b, pushed, 20);
    CHECK(o->out_pm[0] == -400 && o->out_pm[1] == 250);
    k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 1 && fr[0].type == ASGP_MSG_SAMPLE && asgp_get_u16(fr[0].payload) == 700 &&
          (fr[0].payload[4] & ASGP_ST_OVERRIDE_ACTIVE) &&
          asgp_get_u16(fr[0].payload + 5) == o->out_code[0]);

    /* a corrupted frame is ignored and reported once at the next tick */
    n_written = 0;
    uint8_t f[ASGP_MAX_FRAME];
    asgp_put_u16(pl, 900);
    size_t n = asgp_encode(f, ASGP_MSG_OVERRIDE, 3, pl, 4);
    f[6] ^= 0x40;
    for (size_t i = 0; i < n; ++i) {
        asgp_board_rx(&b, f[i], 30);
    }
    o = asgp_board_tick(&b, pushed, 40);
    CHECK(o->out_pm[0] == -400);
    k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 2 && fr[1].type == ASGP_MSG_ERROR && fr[1].payload[0] == ASGP_ERR_BAD_CRC);

    /* unknown type and wrong length are reported, not acted on */
    n_written = 0;
    send_to(&b, 0x42, 4, pl, 2, 50);
    o = asgp_board_tick(&b, pushed, 50);
    k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 2 && fr[1].payload[0] == ASGP_ERR_UNKNOWN_TYPE && fr[1].payload[1] == 0x42);
    n_written = 0;
    send_to(&b, ASGP_MSG_OVERRIDE, 5, pl, 3, 60);
    o = asgp_board_tick(&b, pushed, 60);
    k = feed_all(&p, written, n_written, fr, 64);
    CHECK(k == 2 && fr[1].payload[0] == ASGP_ERR_BAD_LENGTH && o->out_pm[0] == -400);

    /* heartbeats every ASGP_HEARTBEAT_EVERY ticks; sequence numbers count up */
    n_written = 0;
    for (int i = 0; i < ASGP_HEARTBEAT_EVERY; ++i) {
        asgp_board_tick(&b, pushed, 100 + (uint32_t)i * 10);
    }
    k = feed_all(&p, written, n_written, fr, 64);
    int beats = 0;
    for (int i = 0; i < k && i < 64; ++i) {
        beats += fr[i].type == ASGP_MSG_HEARTBEAT;
        if (i > 0) {
            CHECK((uint8_t)(fr[i - 1].seq + 1) == fr[i].seq);
        }
    }
    CHECK(beats == 1);
}

int main(int argc, char **argv)
{
    test_vectors(argc > 1 ? argv[1] : "test/vectors.txt");
    test_parser_resync();
    test_calibration();
    test_watchdog_and_neutral();
    test_board();
    printf("%d checks, %d failures\n", checks, failures);
    return failures ? 1 : 0;
}
