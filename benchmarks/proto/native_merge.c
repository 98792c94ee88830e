/* Prototype for issue 50 (benchmarks/proto_live_path.py): a live run's merge of a batch of events into
 * its open frames in one compiled pass, instead of relay.live.run.LiveRun._merge's few dozen numpy
 * calls. Events are EVENT_DTYPE records as the wire carries them (24 bytes: ts i64, frame i64,
 * source i32, stage i16, point i8, code i8); open rows are found through an open-addressing hash of
 * key = source << 44 | frame. Cells keep each (stage, point)'s earliest time, the group cell the last
 * ready event's code, as frame_table and LiveRun._merge do. */
#include <stdint.h>
#include <string.h>

#define MISSING (-1)
#define CELLS 6
#define EXIT 2
#define READY 3
#define GROUP 5
#define FRAME_POINTS 5
#define KEY_SHIFT 44

#pragma pack(push, 1)
typedef struct { int64_t ts, frame; int32_t source; int16_t stage; int8_t point, code; } event_t;
#pragma pack(pop)

static inline uint64_t mix(uint64_t k) {
    k ^= k >> 33; k *= 0xff51afd7ed558ccdULL; k ^= k >> 33; return k;
}

/* Put key -> row in the hash (mask + 1 slots, a power of two, key -1 free). */
static inline void put(int64_t *hkey, int64_t *hrow, int64_t mask, int64_t key, int64_t row) {
    uint64_t h = mix((uint64_t)key) & (uint64_t)mask;
    while (hkey[h] != -1 && hkey[h] != key) h = (h + 1) & (uint64_t)mask;
    hkey[h] = key; hrow[h] = row;
}

void rebuild(const int64_t *okey, int64_t n, int64_t *hkey, int64_t *hrow, int64_t mask) {
    memset(hkey, 0xff, (size_t)(mask + 1) * sizeof(int64_t));
    for (int64_t r = 0; r < n; r++) put(hkey, hrow, mask, okey[r], r);
}

/* Merge n events. Returns the open row count after, or -1 if a new frame found no room (rows_cap):
 * the caller makes room and merges the rest from *done on. Sources: sorted ids and their watermarks
 * (an unknown source has none). out: [late, newest, done]. */
int64_t merge(const event_t *ev, int64_t n, int n_stages,
              int64_t *hkey, int64_t *hrow, int64_t mask,
              int64_t *okey, int64_t *cells, int64_t *last, int64_t rows, int64_t rows_cap,
              const int64_t *src_ids, const int64_t *watermark, int64_t n_src,
              uint8_t *has_exit, int64_t *out) {
    int64_t late = out[0], newest = out[1];
    for (int64_t i = out[2]; i < n; i++) {
        const event_t *e = &ev[i];
        if (e->point >= FRAME_POINTS || e->point < 0) continue;
        if (e->ts > newest) newest = e->ts;  /* as LiveRun._merge: late events count for these two */
        if (e->point == EXIT) has_exit[e->stage] = 1;
        int64_t key = ((int64_t)e->source << KEY_SHIFT) | e->frame;
        uint64_t h = mix((uint64_t)key) & (uint64_t)mask;
        while (hkey[h] != -1 && hkey[h] != key) h = (h + 1) & (uint64_t)mask;
        int64_t row;
        if (hkey[h] == key) {
            row = hrow[h];
        } else {
            int64_t lo = 0, hi = n_src;  /* the source's watermark: frames at or below it are late */
            while (lo < hi) { int64_t mid = (lo + hi) / 2; if (src_ids[mid] < e->source) lo = mid + 1; else hi = mid; }
            if (lo < n_src && src_ids[lo] == e->source && e->frame <= watermark[lo]) { late++; continue; }
            if (rows >= rows_cap || 2 * (rows + 1) > mask + 1) { out[0] = late; out[1] = newest; out[2] = i; return -1; }
            row = rows++;
            okey[row] = key; last[row] = 0;
            int64_t *c = cells + row * n_stages * CELLS;
            for (int k = 0; k < n_stages * CELLS; k++) c[k] = MISSING;
            hkey[h] = key; hrow[h] = row;
        }
        int64_t *c = cells + (row * n_stages + e->stage) * CELLS;
        if (c[e->point] == MISSING || e->ts < c[e->point]) c[e->point] = e->ts;
        if (e->point == READY) c[GROUP] = e->code;
        if (e->ts > last[row]) last[row] = e->ts;
    }
    out[0] = late; out[1] = newest; out[2] = n;
    return rows;
}
