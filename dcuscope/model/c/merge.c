/* The live engine's merge (relay.live.run.LiveRun): a batch of checked events (batch.c) into a run's
 * open frames, in one pass. Events are EVENT_DTYPE records as the wire carries them (24 bytes: ts i64,
 * frame i64, source i32, stage i16, point i8, code i8). Open rows are found through an open-addressing hash of
 * key = source << 44 | frame (relay.live.opentable.OpenTable keeps it). A cell keeps the earliest time
 * of its (stage, point), the group cell the last ready event's code, as model.frametable's
 * frame_table does offline; relay.live.run.LiveRun's numpy merge does the same where this library
 * could not be built, and tests/relay/live/test_live_merge.py holds the two to one another.
 */
#include <string.h>

#include "core.h"

/* The first of n source ids (int32, stride bytes apart: a field of a batch's records) that is not
 * among the n_src ids of src_ids (sorted), or -1: relay.live.run.LiveRun's check, at every batch,
 * that its sources are known. A run of equal ids is looked up once. */
int64_t dcu_unknown_source(const char *sources, int64_t n, int64_t stride, const int64_t *src_ids, int64_t n_src) {
    int64_t known = -1;
    for (int64_t i = 0; i < n; i++) {
        int32_t s32;
        memcpy(&s32, sources + i * stride, sizeof s32); /* a field of packed records: maybe unaligned */
        int64_t s = s32;
        if (known >= 0 && s == known) continue;
        int64_t lo = 0, hi = n_src;
        while (lo < hi) {
            int64_t mid = lo + (hi - lo) / 2;
            if (src_ids[mid] < s) lo = mid + 1; else hi = mid;
        }
        if (lo == n_src || src_ids[lo] != s) return i;
        known = s;
    }
    return -1;
}


/* Fill the hash (slots = mask + 1, a power of two; key -1 marks a free slot) with the n open keys. */
void dcu_merge_rehash(const int64_t *okey, int64_t n, int64_t *hkey, int64_t *hrow, int64_t mask) {
    memset(hkey, 0xff, (size_t)(mask + 1) * sizeof(int64_t));
    for (int64_t r = 0; r < n; r++) {
        uint64_t h = mix((uint64_t)okey[r]) & (uint64_t)mask;
        while (hkey[h] != -1) h = (h + 1) & (uint64_t)mask;
        hkey[h] = okey[r];
        hrow[h] = r;
    }
}

/* Each of n keys' row (rows_out) and whether it is open (found_out: 1 or 0; the row is meaningless at 0). */
void dcu_merge_locate(const int64_t *keys, int64_t n, const int64_t *hkey, const int64_t *hrow, int64_t mask,
                      int64_t *rows_out, uint8_t *found_out) {
    for (int64_t i = 0; i < n; i++) {
        uint64_t h = mix((uint64_t)keys[i]) & (uint64_t)mask;
        while (hkey[h] != -1 && hkey[h] != keys[i]) h = (h + 1) & (uint64_t)mask;
        found_out[i] = hkey[h] == keys[i];
        rows_out[i] = found_out[i] ? hrow[h] : 0;
    }
}

/* Merge events [io[3], n) into the rows open (rows of rows_cap allocated). Frame events only: drops and
 * facts (point >= FRAME_POINTS) are skipped. An event of a frame not open whose source's watermark
 * (src_ids sorted, watermark beside) is at or above it is late: counted, not merged. Every frame
 * event, late or not, raises newest and marks its stage's exit point.
 *
 * Returns the rows open after. It stops early when a frame must open and there is no row for it
 * (rows_cap), or the hash would pass half full: io[3] < n then says where to go on from once the
 * caller made room (what came before is merged and counted).
 * io: [late, newest, placed, start] in and out (placed: frame events merged into a row). */
int64_t dcu_merge(const event_t *ev, int64_t n, int32_t n_stages,
                  int64_t *hkey, int64_t *hrow, int64_t mask,
                  int64_t *okey, int64_t *cells, int64_t *last, uint8_t *shown, int64_t *end,
                  int64_t rows, int64_t rows_cap,
                  const int64_t *src_ids, const int64_t *watermark, int64_t n_src,
                  uint8_t *has_exit, int64_t *io) {
    int64_t late = io[0], newest = io[1], placed = io[2];
    const int64_t row_cells = (int64_t)n_stages * CELLS;
    int64_t i = io[3];
    for (; i < n; i++) {
        const event_t *e = &ev[i];
        if (e->point < 0 || e->point >= FRAME_POINTS) continue;
        if (e->ts > newest) newest = e->ts;
        if (e->point == EXIT) has_exit[e->stage] = 1;
        int64_t key = ((int64_t)e->source << KEY_SHIFT) | e->frame;
        uint64_t h = mix((uint64_t)key) & (uint64_t)mask;
        while (hkey[h] != -1 && hkey[h] != key) h = (h + 1) & (uint64_t)mask;
        int64_t row;
        if (hkey[h] == key) {
            row = hrow[h];
        } else {
            int64_t lo = 0, hi = n_src;
            while (lo < hi) {
                int64_t mid = lo + (hi - lo) / 2;
                if (src_ids[mid] < e->source) lo = mid + 1; else hi = mid;
            }
            if (lo < n_src && src_ids[lo] == e->source && e->frame <= watermark[lo]) {
                late++;
                continue;
            }
            if (rows >= rows_cap || 2 * (rows + 1) > mask + 1) break;
            row = rows++;
            okey[row] = key;
            last[row] = 0;
            shown[row] = 0;
            end[row] = 0;
            int64_t *c = cells + row * row_cells;
            for (int64_t k = 0; k < row_cells; k++) c[k] = MISSING;
            hkey[h] = key;
            hrow[h] = row;
        }
        int64_t *c = cells + (row * n_stages + e->stage) * CELLS;
        if (c[e->point] == MISSING || e->ts < c[e->point]) c[e->point] = e->ts;
        if (e->point == READY) c[GROUP] = e->code;
        if (e->ts > last[row]) last[row] = e->ts;
        placed++;
    }
    io[0] = late;
    io[1] = newest;
    io[2] = placed;
    io[3] = i;
    return rows;
}

/* The origins of n checked events counted per (source, bin = ts / bin_ns), for the run's accounting and its
 * window (model.facts.Accounting, relay.live.sourcewindow.SourceWindow): m distinct pairs written, in the
 * order they first come, into source, bin and count (room for n each); returns m. *top: the greatest point
 * of the batch (the rare drops and facts are left to numpy). hkey: a hash of mask + 1 >= 2n slots. */
int64_t dcu_origins(const event_t *ev, int64_t n, int64_t bin_ns, int64_t *source, int64_t *bin, int64_t *count,
                    int64_t *hkey, int64_t *hrow, int64_t mask, int64_t *top) {
    int64_t m = 0, hi = -128;
    memset(hkey, 0xff, (size_t)(mask + 1) * sizeof(int64_t));
    for (int64_t i = 0; i < n; i++) {
        const event_t *e = &ev[i];
        if (e->point > hi) hi = e->point;
        if (e->point != ORIGIN) continue;
        int64_t b = e->ts / bin_ns, key = ((int64_t)e->source << 40) | (b & ((1LL << 40) - 1));
        uint64_t h = mix((uint64_t)key) & (uint64_t)mask;
        while (hkey[h] != -1 && hkey[h] != key) h = (h + 1) & (uint64_t)mask;
        if (hkey[h] == key) {
            count[hrow[h]]++;
            continue;
        }
        hkey[h] = key;
        hrow[h] = m;
        source[m] = e->source;
        bin[m] = b;
        count[m++] = 1;
    }
    *top = hi;
    return m;
}
