/* The board's link logic (see board.h). */
#include "board.h"

#include "config.h"

#include <string.h>

static void send(asgp_board_t *b, uint8_t type, const uint8_t *payload, uint8_t len)
{
    uint8_t frame[ASGP_MAX_FRAME];
    size_t n = asgp_encode(frame, type, b->tx_seq++, payload, len);
    b->write(frame, n, b->write_ctx);
}

static void report(asgp_board_t *b, uint8_t code, uint8_t detail)
{
    /* at most one error per tick reaches the host: the latest one */
    b->pending_error = code;
    b->pending_detail = detail;
}

void asgp_board_init(asgp_board_t *b, asgp_write_fn write, void *ctx)
{
    memset(b, 0, sizeof(*b));
    asgp_parser_init(&b->parser);
    asgp_safety_init(&b->safety);
    asgp_default_calibration(b->cal);
    b->write = write;
    b->write_ctx = ctx;
    for (int i = 0; i < 2; ++i) {
        b->out.out_code[i] = (uint16_t)b->cal[i].dac_neutral;
    }
}

static void send_version(asgp_board_t *b)
{
    uint8_t p[ASGP_LEN_VERSION];
    p[0] = ASGP_PROTOCOL_VERSION;
    p[1] = ASGP_FW_MAJOR;
    p[2] = ASGP_FW_MINOR;
    p[3] = ASGP_FW_PATCH;
    asgp_put_u16(p + 4, ASGP_SAMPLE_RATE_HZ);
    asgp_put_u16(p + 6, ASGP_WATCHDOG_MS);
    send(b, ASGP_MSG_VERSION, p, sizeof(p));
}

static void handle(asgp_board_t *b, const asgp_frame_t *f, uint32_t now_ms)
{
    static const uint8_t expected_len[8] = {
        0, ASGP_LEN_SAMPLE, ASGP_LEN_OVERRIDE, ASGP_LEN_MODE,
        ASGP_LEN_HEARTBEAT, ASGP_LEN_HELLO, ASGP_LEN_VERSION, ASGP_LEN_ERROR,
    };
    uint8_t err = 0;
    if (f->type != ASGP_MSG_OVERRIDE && f->type != ASGP_MSG_MODE &&
        f->type != ASGP_MSG_HEARTBEAT && f->type != ASGP_MSG_HELLO) {
        report(b, ASGP_ERR_UNKNOWN_TYPE, f->type);
        return;
    }
    if (f->len != expected_len[f->type]) {
        report(b, ASGP_ERR_BAD_LENGTH, f->type);
        return;
    }
    b->rx_frames++;
    asgp_safety_host_alive(&b->safety, now_ms);
    switch (f->type) {
    case ASGP_MSG_HELLO:
        b->pending_version = 1; /* at the next tick: a flood of HELLOs cannot fill the UART */
        if (f->payload[0] != ASGP_PROTOCOL_VERSION) {
            report(b, ASGP_ERR_VERSION_MISMATCH, f->payload[0]);
        }
        break;
    case ASGP_MSG_MODE:
        err = asgp_safety_set_mode(&b->safety, f->payload[0], now_ms);
        break;
    case ASGP_MSG_OVERRIDE:
        err = asgp_safety_set_override(&b->safety, asgp_get_i16(f->payload),
                                       asgp_get_i16(f->payload + 2), now_ms);
        break;
    default: /* HEARTBEAT: liveness only */
        break;
    }
    if (err) {
        report(b, err, f->seq);
    }
}

/* When the last byte of the frame the parser just returned came: the parser.n bytes it
 * still holds all came after it (the buffer is always the newest bytes received), so it is
 * the (parser.n + 1)th newest byte, at most ASGP_MAX_FRAME - ASGP_HEADER_LEN - ASGP_CRC_LEN
 * back: still in the ring. Not the time of the byte that completed (or of the tick that gave
 * up) the candidate in front of it: that is up to 39 bytes, at 19 ms each, later. */
static uint32_t frame_end_ms(const asgp_board_t *b)
{
    uint8_t back = (uint8_t)(b->parser.n + 1u);
    uint8_t i = (uint8_t)(b->rx_head >= back ? b->rx_head - back
                                             : b->rx_head + ASGP_MAX_FRAME - back);
    return b->rx_ms[i];
}

void asgp_board_rx(asgp_board_t *b, uint8_t byte, uint32_t now_ms)
{
    asgp_frame_t f;
    b->last_rx_ms = now_ms;
    b->rx_ms[b->rx_head] = now_ms;
    b->rx_head = (uint8_t)(b->rx_head + 1u == ASGP_MAX_FRAME ? 0u : b->rx_head + 1u);
    uint16_t crc_before = b->parser.crc_errors;
    int got = asgp_parser_feed(&b->parser, byte, &f);
    if (b->parser.crc_errors != crc_before) {
        report(b, ASGP_ERR_BAD_CRC, 0);
    }
    while (got) {
        handle(b, &f, frame_end_ms(b));
        got = asgp_parser_next(&b->parser, &f);
    }
}

static void expire_rx(asgp_board_t *b)
{
    asgp_frame_t f;
    uint16_t crc_before = b->parser.crc_errors;
    while (b->parser.n > 0) {
        int got = asgp_parser_expire(&b->parser, &f);
        while (got) {
            handle(b, &f, frame_end_ms(b));
            got = asgp_parser_next(&b->parser, &f);
        }
    }
    if (b->parser.crc_errors != crc_before) {
        report(b, ASGP_ERR_BAD_CRC, 0);
    }
}

const asgp_output_t *asgp_board_tick(asgp_board_t *b, const int16_t raw[2], uint32_t now_ms)
{
    if (b->parser.n > 0 && (uint32_t)(now_ms - b->last_rx_ms) >= ASGP_RX_IDLE_MS) {
        expire_rx(b);
    }
    uint8_t was_fault = b->out.status & ASGP_ST_ADC_FAULT;
    asgp_safety_step(&b->safety, b->cal, raw, now_ms, &b->out);
    if ((b->out.status & ASGP_ST_ADC_FAULT) && !was_fault) {
        report(b, ASGP_ERR_ADC_FAULT, 0);
    }
    uint8_t p[ASGP_LEN_HEARTBEAT];
    asgp_put_u16(p, (uint16_t)raw[0]);
    asgp_put_u16(p + 2, (uint16_t)raw[1]);
    p[4] = b->out.status;
    asgp_put_u16(p + 5, b->out.out_code[0]);
    asgp_put_u16(p + 7, b->out.out_code[1]);
    send(b, ASGP_MSG_SAMPLE, p, ASGP_LEN_SAMPLE);

    if (++b->tick_count >= ASGP_HEARTBEAT_EVERY) {
        b->tick_count = 0;
        asgp_put_u32(p, now_ms);
        asgp_put_u16(p + 4, b->rx_frames);
        asgp_put_u16(p + 6, b->parser.crc_errors);
        p[8] = b->safety.mode;
        send(b, ASGP_MSG_HEARTBEAT, p, ASGP_LEN_HEARTBEAT);
    }
    if (b->pending_version) {
        b->pending_version = 0;
        send_version(b);
    }
    if (b->pending_error) {
        uint8_t e[ASGP_LEN_ERROR] = {b->pending_error, b->pending_detail};
        b->pending_error = 0;
        send(b, ASGP_MSG_ERROR, e, ASGP_LEN_ERROR);
    }
    return &b->out;
}
