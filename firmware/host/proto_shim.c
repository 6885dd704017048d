/* proto_shim.c: what ctypes needs besides src/proto.c's own functions (host builds only). */
#include <stddef.h>

#include "proto.h"

size_t proto_decoder_sizeof(void) { return sizeof(proto_decoder_t); }

/* The counters in a fixed order: frames_ok, crc_errors, undecodable, oversize, malformed. */
void proto_decoder_counters(const proto_decoder_t *d, uint16_t out[5])
{
    out[0] = d->frames_ok;
    out[1] = d->crc_errors;
    out[2] = d->undecodable;
    out[3] = d->oversize;
    out[4] = d->malformed;
}

const uint8_t *proto_decoder_packet(const proto_decoder_t *d, uint8_t *len)
{
    *len = d->len;
    return d->buf;
}
