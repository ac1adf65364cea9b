/*
 * The board's link logic without hardware: frames in -> safety state, control ticks ->
 * SAMPLE / HEARTBEAT / ERROR frames out. Plain C99; the sketch supplies the clock, the ADC
 * readings, the DAC and a function that writes bytes to the UART.
 */
#ifndef ASGP_BOARD_H
#define ASGP_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "protocol.h"
#include "safety.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef void (*asgp_write_fn)(const uint8_t *data, size_t len, void *ctx);

typedef struct {
    asgp_parser_t parser;
    asgp_safety_t safety;
    asgp_axis_cal_t cal[2];
    asgp_output_t out;
    uint8_t tx_seq;
    uint8_t pending_error;  /* ASGP_ERR_* to report at the next tick, 0 = none */
    uint8_t pending_detail;
    uint16_t rx_frames;     /* valid frames from the host */
    uint16_t tick_count;
    uint8_t pending_version; /* a HELLO came: VERSION goes out at the next tick (one) */
    uint32_t last_rx_ms;     /* when the last byte came */
    /* when each of the last ASGP_MAX_FRAME bytes came (a ring; rx_head is where the next
     * byte's time goes): a frame is timed by its own last byte, however late the parser
     * finds it (behind a partial frame that more bytes rejected, or that went idle) */
    uint32_t rx_ms[ASGP_MAX_FRAME];
    uint8_t rx_head;
    asgp_write_fn write;
    void *write_ctx;
} asgp_board_t;

void asgp_board_init(asgp_board_t *b, asgp_write_fn write, void *ctx);
/* One received byte; complete frames are acted on at once (a HELLO's VERSION is sent at
 * the next tick: one a tick, whatever the host sends). */
void asgp_board_rx(asgp_board_t *b, uint8_t byte, uint32_t now_ms);
/* One control tick (ASGP_SAMPLE_RATE_HZ): returns the output to write to the DAC. A partial
 * frame idle for ASGP_RX_IDLE_MS is given up first (frames found behind it are acted on,
 * each timed by its own last byte, as every frame is: an override behind line noise never
 * drives the chair ASGP_WATCHDOG_MS or more after its last byte came). */
const asgp_output_t *asgp_board_tick(asgp_board_t *b, const int16_t raw[2], uint32_t now_ms);

#ifdef __cplusplus
}
#endif

#endif /* ASGP_BOARD_H */
