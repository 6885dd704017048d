/* proto.c: protocol v2 framing in plain C99; see proto.h. */
#include "proto.h"

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0), one byte at a
 * time without a table: for this polynomial the table lookup reduces to three shifts of the
 * folded index x (x ^ x>>4 carries the polynomial's x^12 term back into the low nibble). */
uint16_t proto_crc16_byte(uint16_t crc, uint8_t b)
{
    uint8_t x = (uint8_t)((crc >> 8) ^ b);
    x ^= (uint8_t)(x >> 4);
    return (uint16_t)((crc << 8) ^ ((uint16_t)x << 12) ^ ((uint16_t)x << 5) ^ x);
}

uint16_t proto_crc16(uint16_t crc, const uint8_t *p, uint8_t n)
{
    while (n--)
        crc = proto_crc16_byte(crc, *p++);
    return crc;
}

int8_t proto_payload_ok(uint8_t type, uint8_t n)
{
    switch (type) {
    case PT_HELLO: return n == PL_HELLO;
    case PT_DRIVE: return n == PL_DRIVE;
    case PT_STOP: return n == PL_STOP;
    case PT_HELLO_REPLY: return n == PL_HELLO_REPLY || n == PL_HELLO_REPLY_V1;
    case PT_STATE: return n == PL_STATE || n == PL_STATE_V1;
    default: return -1;
    }
}

static void restart(proto_decoder_t *d)
{
    d->len = 0;
    d->frame_len = 0;
    d->run = 0;
    d->code = 0;
    d->overflow = 0;
}

void proto_decoder_init(proto_decoder_t *d)
{
    restart(d);
    d->frames_ok = 0;
    d->crc_errors = 0;
    d->undecodable = 0;
    d->oversize = 0;
    d->malformed = 0;
}

uint16_t proto_decoder_errors(const proto_decoder_t *d)
{
    return (uint16_t)(d->crc_errors + d->undecodable + d->oversize + d->malformed);
}

/* A frame ended (0x00 seen): classify it exactly as hal/protocol.py's FrameDecoder does. */
static uint8_t end_frame(proto_decoder_t *d)
{
    uint8_t ok = 0;
    if (d->overflow) {
        d->oversize++;
    } else if (d->frame_len == 0) {
        /* empty frame: ignored, not an error */
    } else if (d->run != 0) {
        d->undecodable++; /* the last code byte runs past the end of the frame */
    } else if (d->len < 4u) {
        d->undecodable++; /* shorter than type + seq + crc */
    } else {
        uint8_t body = (uint8_t)(d->len - 2u);
        uint16_t crc = proto_get_u16(&d->buf[body]);
        if (proto_crc16(0xFFFFu, d->buf, body) != crc) {
            d->crc_errors++;
        } else {
            if (proto_payload_ok(d->buf[0], (uint8_t)(body - 2u)) == 0) {
                d->malformed++;
            } else {
                d->frames_ok++;
                ok = 1;
            }
        }
    }
    if (ok) {
        /* keep buf and len for the caller; reset the rest for the next frame */
        uint8_t len = d->len;
        restart(d);
        d->len = len;
        return 1;
    }
    restart(d);
    return 0;
}

uint8_t proto_decoder_feed(proto_decoder_t *d, uint8_t b)
{
    if (b == 0)
        return end_frame(d);
    if (d->frame_len == 0)
        d->len = 0; /* a new frame: the previous packet's bytes are gone */
    if (d->overflow)
        return 0;
    if (d->frame_len >= PROTO_MAX_FRAME) {
        d->overflow = 1;
        return 0;
    }
    d->frame_len++;
    if (d->run == 0) {
        /* a code byte: the previous run (if any) ended with an implied zero unless its
         * code was 0xFF; a frame's very last run has none (decided at the delimiter) */
        if (d->frame_len > 1u && d->code != 0xFFu)
            d->buf[d->len++] = 0; /* len < 64 here: 65 COBS bytes decode to at most 64 */
        d->code = b;
        d->run = (uint8_t)(b - 1u);
    } else {
        d->buf[d->len++] = b;
        d->run--;
    }
    return 0;
}

uint8_t proto_encode_frame(uint8_t type, uint8_t seq, const uint8_t *payload, uint8_t n, uint8_t *out)
{
    if (n > PROTO_MAX_PACKET - 4u)
        return 0;
    uint16_t crc = proto_crc16_byte(0xFFFFu, type);
    crc = proto_crc16_byte(crc, seq);
    crc = proto_crc16(crc, payload, n);
    uint8_t total = (uint8_t)(n + 4u);
    uint8_t code_pos = 0;
    uint8_t o = 1;
    uint8_t code = 1;
    for (uint8_t i = 0; i < total; i++) {
        uint8_t c;
        if (i == 0)
            c = type;
        else if (i == 1)
            c = seq;
        else if (i < total - 2u)
            c = payload[i - 2u];
        else if (i == total - 2u)
            c = (uint8_t)crc;
        else
            c = (uint8_t)(crc >> 8);
        if (c == 0) {
            out[code_pos] = code;
            code_pos = o++;
            code = 1;
        } else {
            out[o++] = c;
            if (++code == 0xFFu) { /* cannot happen within 64 bytes; kept for the rule */
                out[code_pos] = code;
                code_pos = o++;
                code = 1;
            }
        }
    }
    out[code_pos] = code;
    out[o++] = 0;
    return o;
}

uint8_t proto_parse_drive(const uint8_t *payload, proto_drive_t *out)
{
    int16_t l = proto_get_i16(payload);
    int16_t r = proto_get_i16(payload + 2);
    uint16_t t = proto_get_u16(payload + 4);
    if (l < -PROTO_DUTY_FULL || l > PROTO_DUTY_FULL || r < -PROTO_DUTY_FULL || r > PROTO_DUTY_FULL)
        return 0;
    if (t < PROTO_TIMEOUT_MIN || t > PROTO_TIMEOUT_MAX)
        return 0;
    out->duty_l = l;
    out->duty_r = r;
    out->timeout_ms = t;
    return 1;
}
