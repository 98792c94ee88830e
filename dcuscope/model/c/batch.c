/* A wire batch decoded and checked (protocol.wire: decode_batch and check_events, which say what is
 * wrong with a batch this refuses). The 40-byte header, then count events of 24 bytes:
 *   0 magic "DCUB" | 4 version | 5 flags | 6 reserved u16 | 8 run id (16) | 24 seq u64 | 32 count u32 | 36 length u32 */
#include <string.h>

#include "core.h"

#define HEADER_SIZE 40
#define BATCH_VERSION 1
#define FLAG_ZLIB 1

int dcu_core_abi(void) { return CORE_ABI; }

int dcu_event_size(void) { return (int)sizeof(event_t); }

/* The first of n events a pipeline cannot produce, or -1: protocol.wire.check_events in one pass.
 * codes: [256 points][256 codes as bytes], whether a point allows a code (no point out of range does). */
int64_t dcu_check(const event_t *ev, int64_t n, int32_t n_stages, const uint8_t *codes, int64_t source_limit,
                  int64_t frame_limit) {
    for (int64_t i = 0; i < n; i++) {
        const event_t *e = &ev[i];
        if (!codes[(uint8_t)e->point * 256 + (uint8_t)e->code] || e->stage < 0 || e->stage >= n_stages
            || e->source < 0 || e->source >= source_limit || e->frame < 0 || e->frame >= frame_limit || e->ts <= 0)
            return i;
    }
    return -1;
}

static uint64_t le(const uint8_t *p, int bytes) {
    uint64_t v = 0;
    for (int i = bytes - 1; i >= 0; i--) v = v << 8 | p[i];
    return v;
}

/* Decode the batch of len bytes at data: out = [seq, count, flags, first invalid event or -1].
 * Returns DCU_BATCH_OK (its events, at data + 40, checked), DCU_BATCH_INFLATE (the header is sound,
 * the payload zlib: the caller inflates it, at most count events, and checks them), or a DCU_BATCH_*
 * fault (negative); out holds what was read up to it. */
int dcu_decode_batch(const uint8_t *data, int64_t len, int32_t n_stages, int64_t max_events, const uint8_t *codes,
                     int64_t source_limit, int64_t frame_limit, int64_t *out) {
    out[0] = out[1] = out[2] = 0;
    out[3] = -1;
    if (len < HEADER_SIZE) return -1;
    if (memcmp(data, "DCUB", 4) != 0) return -2;
    if (data[4] != BATCH_VERSION) return -3;
    out[2] = data[5];
    if ((data[5] & ~FLAG_ZLIB) || le(data + 6, 2)) return -4;
    uint64_t seq = le(data + 24, 8), count = le(data + 32, 4), length = le(data + 36, 4);
    out[1] = (int64_t)count;
    if (count == 0 || count > (uint64_t)max_events) return -5;
    if (seq > (uint64_t)INT64_MAX) return -6;
    out[0] = (int64_t)seq;
    if (length != (uint64_t)(len - HEADER_SIZE)) return -7;
    if (data[5] & FLAG_ZLIB) return 1;
    if (length != count * sizeof(event_t)) return -8;
    out[3] = dcu_check((const event_t *)(data + HEADER_SIZE), (int64_t)count, n_stages, codes, source_limit, frame_limit);
    return out[3] >= 0 ? -9 : 0;
}
