/* proto.h: protocol v2 (docs/protocol.md) in plain C99: CRC-16/CCITT-FALSE, COBS framing,
 * a byte-at-a-time frame decoder and the packet encoder. No hardware, no dynamic memory:
 * the firmware uses it on the AVR and tests/test_firmware_proto.py holds the same file,
 * compiled for the host, byte for byte against hal/protocol.py.
 */
#ifndef DDRT_PROTO_H
#define DDRT_PROTO_H

#include <stdint.h>

#define PROTO_VERSION 2
#define PROTO_MAX_PACKET 64u /* type + seq + payload + crc, before COBS */
#define PROTO_MAX_FRAME 65u  /* COBS bytes of the longest packet, without the delimiter */
#define PROTO_MAX_WIRE (PROTO_MAX_FRAME + 1u) /* ... and with it */
#define PROTO_DUTY_FULL 10000
#define PROTO_TIMEOUT_MIN 1u
#define PROTO_TIMEOUT_MAX 1000u

#define PT_HELLO 0x01u
#define PT_DRIVE 0x02u
#define PT_STOP 0x03u
#define PT_HELLO_REPLY 0x81u
#define PT_STATE 0x82u

#define PL_HELLO 0u
#define PL_DRIVE 6u
#define PL_STOP 0u
#define PL_HELLO_REPLY 12u
#define PL_STATE 20u
#define PL_HELLO_REPLY_V1 7u /* what a v1 MCU sends; a v2 receiver accepts both lengths */
#define PL_STATE_V1 10u

#define FLAG_WATCHDOG 0x01u
#define FLAG_OUTPUTS_ON 0x02u
#define FLAG_BAD_FRAME 0x04u
#define FLAG_HW_ESTOP 0x08u

#define FEATURE_BATTERY 0x01u  /* STATE.battery_mv is measured */
#define FEATURE_HW_ESTOP 0x02u /* a hardware estop input is wired */
#define FEATURE_WHEELS 0x04u   /* the drive wheels' encoders are counted */

uint16_t proto_crc16_byte(uint16_t crc, uint8_t b);
uint16_t proto_crc16(uint16_t crc, const uint8_t *p, uint8_t n);

/* 1: a known type with a payload of a length it defines (either version's, for 0x81 and
 * 0x82); 0: a known type with another length (malformed); -1: a type not defined. */
int8_t proto_payload_ok(uint8_t type, uint8_t n);

typedef struct {
    uint8_t buf[PROTO_MAX_PACKET]; /* decoded packet: type, seq, payload, crc */
    uint8_t len;                   /* decoded bytes so far */
    uint8_t frame_len;             /* COBS bytes of this frame so far */
    uint8_t run;                   /* data bytes left in the current COBS run */
    uint8_t code;                  /* code byte of the current run */
    uint8_t overflow;              /* frame longer than PROTO_MAX_FRAME: drop to the next 0x00 */
    /* what happened to the frames so far (wrapping counters) */
    uint16_t frames_ok;
    uint16_t crc_errors;
    uint16_t undecodable; /* bad COBS, or shorter than header + CRC */
    uint16_t oversize;
    uint16_t malformed; /* valid CRC, known type, wrong payload length */
} proto_decoder_t;

void proto_decoder_init(proto_decoder_t *d);

/* Feed one byte. Returns 1 when it completed a valid packet: then d->buf[0] is the type,
 * d->buf[1] the seq, the payload starts at d->buf[2] and is proto_packet_payload_len(d)
 * bytes long (valid until the next call). Returns 0 otherwise. */
uint8_t proto_decoder_feed(proto_decoder_t *d, uint8_t b);

static inline uint8_t proto_packet_payload_len(const proto_decoder_t *d) { return (uint8_t)(d->len - 4u); }

/* Sum of the error counters (wrapping): a change means a frame was dropped. */
uint16_t proto_decoder_errors(const proto_decoder_t *d);

/* Encode one packet as it goes on the wire: COBS of (type, seq, payload, crc) and the 0x00
 * delimiter. `out` must hold PROTO_MAX_WIRE bytes. Returns the byte count, or 0 when the
 * payload does not fit one packet. */
uint8_t proto_encode_frame(uint8_t type, uint8_t seq, const uint8_t *payload, uint8_t n, uint8_t *out);

/* Little-endian field access. */
static inline uint16_t proto_get_u16(const uint8_t *p) { return (uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }
static inline int16_t proto_get_i16(const uint8_t *p) { return (int16_t)proto_get_u16(p); }
static inline void proto_put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static inline void proto_put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

/* DRIVE payload, checked against the range rules (all fields or nothing). */
typedef struct {
    int16_t duty_l;
    int16_t duty_r;
    uint16_t timeout_ms;
} proto_drive_t;

/* Returns 1 and fills `out` when every field is in range, 0 otherwise (ignore the DRIVE). */
uint8_t proto_parse_drive(const uint8_t *payload, proto_drive_t *out);

#endif
