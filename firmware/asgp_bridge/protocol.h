/*
 * asgp link protocol: frame layout, message types, CRC-16/CCITT-FALSE and a streaming
 * parser. Plain C99, no Arduino API: compiled into the sketch by avr-gcc and into the
 * host unit tests by gcc. docs/serial_protocol.md is the specification; the Python codec
 * (asgp_ros/serial/protocol.py) mirrors every constant here and a test checks they agree.
 *
 * Frame (all multi-byte fields little-endian):
 *   0xA5 0x5A | LEN (payload bytes, 0..32) | TYPE | SEQ | PAYLOAD[LEN] | CRC16 lo | CRC16 hi
 * CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0) over
 * LEN, TYPE, SEQ and PAYLOAD, i.e. everything between the sync marker and the CRC.
 */
#ifndef ASGP_PROTOCOL_H
#define ASGP_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ASGP_SYNC0 0xA5
#define ASGP_SYNC1 0x5A
#define ASGP_PROTOCOL_VERSION 1
#define ASGP_HEADER_LEN 5
#define ASGP_CRC_LEN 2
#define ASGP_MAX_PAYLOAD 32
#define ASGP_MAX_FRAME (ASGP_HEADER_LEN + ASGP_MAX_PAYLOAD + ASGP_CRC_LEN)

/* message types */
#define ASGP_MSG_SAMPLE 0x01    /* board -> host, 9 bytes */
#define ASGP_MSG_OVERRIDE 0x02  /* host -> board, 4 bytes */
#define ASGP_MSG_MODE 0x03      /* host -> board, 1 byte */
#define ASGP_MSG_HEARTBEAT 0x04 /* both ways, 9 bytes */
#define ASGP_MSG_HELLO 0x05     /* host -> board, 1 byte */
#define ASGP_MSG_VERSION 0x06   /* board -> host, 8 bytes */
#define ASGP_MSG_ERROR 0x07     /* board -> host, 2 bytes */

#define ASGP_LEN_SAMPLE 9
#define ASGP_LEN_OVERRIDE 4
#define ASGP_LEN_MODE 1
#define ASGP_LEN_HEARTBEAT 9
#define ASGP_LEN_HELLO 1
#define ASGP_LEN_VERSION 8
#define ASGP_LEN_ERROR 2

/* modes */
#define ASGP_MODE_PASSTHROUGH 0
#define ASGP_MODE_OVERRIDE 1

/* SAMPLE status bits */
#define ASGP_ST_MODE_OVERRIDE 0x01   /* mode is override */
#define ASGP_ST_OVERRIDE_ACTIVE 0x02 /* the output is the host's override */
#define ASGP_ST_WATCHDOG 0x04        /* override mode, but no fresh override: passthrough */
#define ASGP_ST_NEUTRAL_STOP 0x08    /* user joystick at neutral: output forced neutral */
#define ASGP_ST_CLAMPED 0x10         /* an output was clamped to the safe range */
#define ASGP_ST_ADC_FAULT 0x20       /* joystick reading implausible: output neutral */
#define ASGP_ST_HOST_LOST 0x40       /* no frame from the host for ASGP_HOST_TIMEOUT_MS */

/* ERROR codes */
#define ASGP_ERR_BAD_CRC 1
#define ASGP_ERR_BAD_LENGTH 2
#define ASGP_ERR_UNKNOWN_TYPE 3
#define ASGP_ERR_VERSION_MISMATCH 4
#define ASGP_ERR_OVERRIDE_RANGE 5
#define ASGP_ERR_NOT_IN_OVERRIDE 6
#define ASGP_ERR_ADC_FAULT 7
#define ASGP_ERR_BAD_MODE 8

/* override deflection unit: per mille of full deflection, |value| <= 1000 */
#define ASGP_PERMILLE 1000

uint16_t asgp_crc16(const uint8_t *data, size_t len);
uint16_t asgp_crc16_update(uint16_t crc, uint8_t byte);

/* Writes a whole frame into out (at least ASGP_HEADER_LEN + len + ASGP_CRC_LEN bytes);
 * returns the frame length, or 0 if len > ASGP_MAX_PAYLOAD. */
size_t asgp_encode(uint8_t *out, uint8_t type, uint8_t seq, const uint8_t *payload,
                   uint8_t len);

typedef struct {
    uint8_t type;
    uint8_t seq;
    uint8_t len;
    uint8_t payload[ASGP_MAX_PAYLOAD];
} asgp_frame_t;

typedef struct {
    uint8_t buf[ASGP_MAX_FRAME];
    uint8_t n;
    uint16_t frames_ok;
    uint16_t crc_errors;
    uint16_t bytes_dropped;
} asgp_parser_t;

void asgp_parser_init(asgp_parser_t *p);

/* Feeds one byte; returns 1 and fills *frame when it completes a frame with a valid CRC.
 * Garbage and frames with a bad CRC or an impossible length are dropped one byte at a
 * time, so a valid frame that starts inside a corrupted one is still found. */
int asgp_parser_feed(asgp_parser_t *p, uint8_t byte, asgp_frame_t *frame);

/* After a frame was returned, the buffer may already hold another complete frame (found
 * while rescanning a corrupted one): call this until it returns 0 to get them in order. */
int asgp_parser_next(asgp_parser_t *p, asgp_frame_t *frame);

/* Gives up the partial frame at the start of the buffer (its rest is not coming: the line
 * went idle): drops one byte and rescans, as for a bad CRC. Returns 1 and fills *frame for
 * a complete frame found (then call asgp_parser_next for more); call again while bytes
 * are held, every one of them stale. */
int asgp_parser_expire(asgp_parser_t *p, asgp_frame_t *frame);

/* little-endian helpers */
static inline void asgp_put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFF);
    p[1] = (uint8_t)(v >> 8);
}
static inline void asgp_put_u32(uint8_t *p, uint32_t v)
{
    asgp_put_u16(p, (uint16_t)(v & 0xFFFF));
    asgp_put_u16(p + 2, (uint16_t)(v >> 16));
}
static inline uint16_t asgp_get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}
static inline int16_t asgp_get_i16(const uint8_t *p) { return (int16_t)asgp_get_u16(p); }

#ifdef __cplusplus
}
#endif

#endif /* ASGP_PROTOCOL_H */
