/* Fuzz harness of the compiled core (dcuscope/model/c): one input is a stage count, a link graph and
 * a wire batch, taken the way the relay takes it: decoded and checked (batch.c); if sound, its events
 * merged into a small open table that grows as the relay's does (merge.c), its keys located, its
 * sources looked up; then the open frames judged by the delay model (judge.c), as a table and as a push
 * tick judges them, and their pushed columns moved to the relay's clock (push.c); the judged frames'
 * delay series gathered and summarized, the delays judged, and the batch's own bytes taken as values
 * (NaN, infinities, anything), summarized as series and as whole-run series with open frames' values
 * (stats.c). Built with
 * AddressSanitizer and UndefinedBehaviorSanitizer, any read or write outside an array, or any
 * undefined behaviour, aborts with a report.
 *
 * libFuzzer's entry point, LLVMFuzzerTestOneInput; without clang's -fsanitize=fuzzer, main() below
 * drives it: random mutations of the seed inputs (files in a folder) for a bounded time.
 *   input: byte 0 stages (1 + b % 12) | byte 1 links (b % 8 pairs, 0: one chain) | 2 bytes per link | batch */
#include <math.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "core.h"

#define MAX_EVENTS 4096
#define SOURCE_LIMIT (1LL << 19)
#define FRAME_LIMIT (1LL << 44)

static uint8_t codes[256 * 256];
long long reached_merge, reached_judge, reached_push, reached_stats, reached_series;

static void *grow(void *p, size_t bytes) {
    void *q = realloc(p, bytes);
    if (!q) abort();
    return q;
}

static int cmp64(const void *a, const void *b) {
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

typedef struct {
    int64_t rows, cap, mask, *hkey, *hrow, *key, *cells, *last, *end;
    uint8_t *shown;
} table_t;

static void room(table_t *t, int s) {
    int64_t cap = t->cap ? 2 * t->cap : 4;
    t->key = grow(t->key, cap * 8);
    t->cells = grow(t->cells, cap * s * CELLS * 8);
    t->last = grow(t->last, cap * 8);
    t->end = grow(t->end, cap * 8);
    t->shown = grow(t->shown, cap);
    t->cap = cap;
    int64_t slots = 16;
    while (slots < 2 * (cap + 1)) slots *= 2;
    t->hkey = grow(t->hkey, slots * 8);
    t->hrow = grow(t->hrow, slots * 8);
    t->mask = slots - 1;
    dcu_merge_rehash(t->key, t->rows, t->hkey, t->hrow, t->mask);
}

/* values[0:n] summarized as k series (exact-size copies: the core reorders them), then as two whole-run
 * series: the first half held (its first quarter sorted, the rest new) and the second half their open
 * frames' values. */
static void summarize_values(const double *values, int64_t n, int64_t k) {
    double *v = malloc(n * 8 + 8), *out = malloc((k > 2 ? k : 2) * SUMMARY * 8);  /* k series, then 2 */
    int64_t *off = malloc((k + 1) * 8);
    memcpy(v, values, n * 8);
    for (int64_t i = 0; i <= k; i++) off[i] = i * n / k;
    dcu_summarize(v, off, k, out);
    int64_t na = n / 2, sorted = na / 4;
    memcpy(v, values, n * 8);
    for (int64_t i = 1; i < sorted; i++) /* an insertion sort of the held part (no NaN there: kept apart) */
        for (int64_t j = i; j > 0 && !(v[j - 1] <= v[j]); j--) {
            double t = isnan(v[j]) ? 0 : v[j];
            v[j] = isnan(v[j - 1]) ? 0 : v[j - 1];
            v[j - 1] = t;
        }
    double *held[2] = {v, v + na}, held_ns[2] = {0, 0}, *scratch = malloc(n * 8 + 8);
    int64_t n_sorted[2] = {sorted, 0}, n_held[2] = {na, 0}, eoff[3] = {0, n - na, n - na};
    double *extra = malloc((n - na) * 8 + 8);
    memcpy(extra, values + na, (n - na) * 8);
    dcu_summarize_held(held, n_sorted, n_held, held_ns, extra, eoff, 2, scratch, out);
    reached_stats++;
    void *all[] = {v, out, off, scratch, extra};
    for (size_t i = 0; i < sizeof all / sizeof *all; i++) free(all[i]);
}

/* The delay series of the n frames j judged gathered (first: their ready cells), then summarized; the
 * arrays exactly as large as dcu_series says it needs. */
static void gather_series(const judge_t *j, const int64_t *ready) {
    const int64_t n = j->n, s = j->s;
    double *out = malloc(n * (4 * s + 1) * 8 + 8), *busy = malloc(s * 8), *scratch = malloc(n * 8 + 8);
    int64_t *rows = malloc((1 + 3 * s + s * s) * 4 * 8), *pairs = malloc(s * s * 8), *off = malloc((2 + 3 * s + s * s) * 8);
    uint8_t *first = malloc(n * s + 1);
    for (int64_t i = 0; i < n * s; i++) first[i] = ready[i] != MISSING;
    int64_t k = dcu_series(n, (int32_t)s, j->delay, j->gap, j->service, j->wait, j->glass, j->prev, first, j->has_exit,
                           out, rows, busy, pairs, scratch);
    if (k < 1 || k > 1 + 3 * s + s * s) abort();
    off[0] = 0;
    for (int64_t i = 0; i < k; i++) off[i + 1] = off[i] + rows[4 * i + 3];
    if (off[k] > n * (4 * s + 1)) abort();
    double *summary = malloc(k * SUMMARY * 8);
    dcu_summarize(out, off, k, summary);
    reached_series++;
    void *all[] = {out, busy, scratch, rows, pairs, off, first, summary};
    for (size_t i = 0; i < sizeof all / sizeof *all; i++) free(all[i]);
}

static void judge_open(const table_t *t, int s, const int32_t *links, int n_links, const uint8_t *has_exit) {
    int64_t n = t->rows;
    int64_t *origin = malloc(n * 8 + 8), *ostage = malloc(n * 8 + 8), *capture = malloc(n * 8 + 8);
    int64_t *enter = malloc(n * s * 8 + 8), *exit_ = malloc(n * s * 8 + 8), *ready = malloc(n * s * 8 + 8);
    for (int64_t r = 0; r < n; r++) {
        const int64_t *c = t->cells + r * s * CELLS;
        ostage[r] = -1;
        origin[r] = capture[r] = MISSING;
        for (int k = 0; k < s; k++) {
            if (ostage[r] < 0 && c[k * CELLS + ORIGIN] != MISSING) {
                ostage[r] = k;
                origin[r] = c[k * CELLS + ORIGIN];
                capture[r] = c[k * CELLS + CAPTURE];
            }
            enter[r * s + k] = c[k * CELLS + ENTER];
            exit_[r * s + k] = c[k * CELLS + EXIT];
            ready[r * s + k] = c[k * CELLS + READY];
        }
    }
    judge_t j = {.n = n, .s = s, .origin = origin, .origin_stage = ostage, .capture = capture, .enter = enter,
                 .exit = exit_, .ready = ready, .has_exit = has_exit, .links = links, .n_links = n_links};
    j.t_out = malloc(n * s * 8 + 8);
    j.prev = malloc(n * s * 8 + 8);
    j.end = malloc(n * 8 + 8);
    j.passed = malloc(n * s + 1);
    j.complete = malloc(n + 1);
    j.delay = malloc(n * s * 8 + 8);
    j.gap = malloc(n * s * 8 + 8);
    j.service = malloc(n * s * 8 + 8);
    j.wait = malloc(n * s * 8 + 8);
    j.frame = malloc(n * 8 + 8);
    j.glass = malloc(n * 8 + 8);
    j.scratch = malloc(2 * s);
    int complete = dcu_judge(&j);
    if (complete < 0 || complete > n) abort();
    reached_judge++;
    gather_series(&j, ready);
    summarize_values(j.delay, n * s, s);
    summarize_values(j.frame, n, 1);
    void *all[] = {origin, ostage, capture, enter, exit_, ready, j.t_out, j.prev, j.end, j.passed, j.complete,
                   j.delay, j.gap, j.service, j.wait, j.frame, j.glass, j.scratch};
    for (size_t i = 0; i < sizeof all / sizeof *all; i++) free(all[i]);
}

/* The open rows judged as a push tick judges them (every other row), and their columns moved by a clock
 * correction whose segments the input's own bytes make: the arrays exactly as large as the calls need. */
static void judge_and_push(const table_t *t, int s, const int32_t *links, int n_links, const uint8_t *has_exit,
                           const uint8_t *bytes, int64_t len) {
    int64_t k = (t->rows + 1) / 2, ir = INT_ROWS(s), fr = FLOAT_ROWS(s);
    int64_t *rows = malloc(k * 8 + 8), *end = malloc(k * 8 + 8), *work = malloc((10 * s + 8) * 8);
    int64_t *ints = malloc(ir * k * 8 + 8), *ints_fm = malloc(ir * k * 8 + 8), *ints_out = malloc(ir * k * 8 + 8);
    double *floats = malloc(fr * k * 8 + 8), *floats_fm = malloc(fr * k * 8 + 8), *floats_out = malloc(fr * k * 8 + 8);
    uint8_t *complete = malloc(k + 1);
    for (int64_t i = 0; i < k; i++) rows[i] = 2 * i;
    int64_t c = dcu_judge_rows(t->cells, t->key, rows, k, s, has_exit, links, n_links, complete, end, ints, floats, work);
    if (c < 0 || c > k) abort();
    for (int64_t i = 0; i < k; i++) { /* field-major to frame-major, as the engine keeps them */
        for (int64_t r = 0; r < ir; r++) ints_fm[i * ir + r] = ints[r * k + i];
        for (int64_t r = 0; r < fr; r++) floats_fm[i * fr + r] = floats[r * k + i];
    }
    int64_t n_seg = len % 4, from[4], ref[4], offset[4], unc[4];
    double drift[4], growth[4];
    for (int64_t g = 0; g < n_seg; g++) {
        int64_t v = 0;
        memcpy(&v, bytes + (g * 8) % (len > 8 ? len - 8 : 1), len >= 8 ? 8 : 0);
        from[g] = g == 0 ? v : from[g - 1] + (v & 0xffffffff);
        ref[g] = v ^ 0x5555, offset[g] = v >> 3, unc[g] = v & 0xffff;
        drift[g] = (double)(v % 200000), growth[g] = (double)(v & 1023);
    }
    dcu_push_columns(ints_fm, floats_fm, k, s, from, ref, offset, drift, unc, growth, n_seg, len, ints_out, floats_out);
    reached_push++;
    void *all[] = {rows, end, work, ints, ints_fm, ints_out, floats, floats_fm, floats_out, complete};
    for (size_t i = 0; i < sizeof all / sizeof *all; i++) free(all[i]);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    if (!codes[0])
        for (int p = 0; p <= 8; p++) memset(codes + p * 256, 1, 256);
    if (size < 2) return 0;
    int s = 1 + data[0] % 12, n_links = data[1] % 8;
    if (size < 2 + 2 * (size_t)n_links) return 0;
    int32_t links[16];
    for (int l = 0; l < n_links; l++) {
        links[2 * l] = (int8_t)data[2 + 2 * l] % 14;      /* some out of range, some negative */
        links[2 * l + 1] = (int8_t)data[3 + 2 * l] % 14;
    }
    const uint8_t *batch = data + 2 + 2 * n_links;
    int64_t len = (int64_t)(size - 2 - 2 * n_links), head[4];
    int code = dcu_decode_batch(batch, len, s, MAX_EVENTS, codes, SOURCE_LIMIT, FRAME_LIMIT, head);
    if (len >= 8) { /* the bytes as values: whatever a hostile node could make its delays */
        double *values = malloc(len);
        memcpy(values, batch, len / 8 * 8);
        summarize_values(values, len / 8, 1 + data[1] % 5);
        free(values);
    }
    if (code != 0) return 0;
    int64_t n = head[1];
    event_t *ev = malloc(n * sizeof(event_t));
    memcpy(ev, batch + 40, n * sizeof(event_t));
    if (dcu_check(ev, n, s, codes, SOURCE_LIMIT, FRAME_LIMIT) != -1) abort(); /* decode checked them */
    reached_merge++;

    /* The run's sources, sorted, each with a watermark from the input (frames at or below are late). */
    int64_t *ids = malloc(n * 8), *mark = malloc(n * 8), n_src = 0;
    for (int64_t i = 0; i < n; i++) ids[i] = ev[i].source;
    qsort(ids, n, 8, cmp64);
    for (int64_t i = 0; i < n; i++)
        if (i == 0 || ids[i] != ids[n_src - 1]) ids[n_src++] = ids[i];
    for (int64_t i = 0; i < n_src; i++) mark[i] = (ids[i] & 3) == 0 ? ev[i % n].frame / 2 : -1;
    if (dcu_unknown_source((const char *)&ev[0].source, n, sizeof(event_t), ids, n_src) != -1) abort();

    table_t t = {0};
    room(&t, s);
    uint8_t has_exit[16] = {0};
    int64_t io[4] = {0, 0, 0, 0};
    for (;;) {
        t.rows = dcu_merge(ev, n, s, t.hkey, t.hrow, t.mask, t.key, t.cells, t.last, t.shown, t.end, t.rows, t.cap,
                           ids, mark, n_src, has_exit, io);
        if (io[3] == n) break;
        room(&t, s);
    }
    int64_t *keys = malloc(n * 8 + 8), *rows = malloc(n * 8 + 8);
    uint8_t *found = malloc(n + 1);
    for (int64_t i = 0; i < n; i++) keys[i] = ((int64_t)ev[i].source << KEY_SHIFT) | ev[i].frame;
    dcu_merge_locate(keys, n, t.hkey, t.hrow, t.mask, rows, found);
    for (int64_t i = 0; i < n; i++)
        if (found[i] && (rows[i] < 0 || rows[i] >= t.rows || t.key[rows[i]] != keys[i])) abort();
    judge_open(&t, s, links, n_links, has_exit);
    judge_and_push(&t, s, links, n_links, has_exit, batch, len);

    void *all[] = {ev, ids, mark, keys, rows, found, t.hkey, t.hrow, t.key, t.cells, t.last, t.end, t.shown};
    for (size_t i = 0; i < sizeof all / sizeof *all; i++) free(all[i]);
    return 0;
}

#ifndef LIBFUZZER
/* The driver without libFuzzer: fuzz_core SECONDS SEED... runs random mutations of the seeds for
 * SECONDS (or SEED... once each with SECONDS 0), then prints how many inputs reached each stage. */
#include <time.h>

static uint64_t rng_state = 0x9e3779b97f4a7c15ULL;

static uint64_t rnd(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

static uint8_t *read_file(const char *path, size_t *size) {
    FILE *f = fopen(path, "rb");
    if (!f) return NULL;
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    uint8_t *buf = malloc(n > 0 ? n : 1);
    *size = fread(buf, 1, n, f);
    fclose(f);
    return buf;
}

/* One input, mutated from a seed: flipped bits, bytes set to edge values, records copied over one
 * another, bytes cut or added; the header's length and count made to agree half the time, so that
 * most inputs go past the decoding into the merge and the judge. */
static size_t mutate(const uint8_t *seed, size_t size, uint8_t *out, size_t room) {
    size_t n = size < room ? size : room;
    memcpy(out, seed, n);
    static const uint8_t edge[] = {0, 1, 0x7f, 0x80, 0xff, 0xfe, 12, 13};
    for (int k = 1 + rnd() % 8; k > 0 && n > 0; k--) {
        size_t at = rnd() % n;
        switch (rnd() % 7) {
        case 0: out[at] ^= (uint8_t)(1u << (rnd() % 8)); break;
        case 1: out[at] = edge[rnd() % sizeof edge]; break;
        case 2: out[at] = (uint8_t)rnd(); break;
        case 3: { /* one 24-byte record over another */
            size_t from = rnd() % n, len = 24;
            if (from + len <= n && at + len <= n) memmove(out + at, out + from, len);
            break;
        }
        case 4: n = at; break;
        case 5: if (n + 24 <= room) { memmove(out + at + 24, out + at, n - at); n += 24; } break;
        default: memset(out + at, 0xff, (n - at) < 8 ? n - at : 8); break;
        }
    }
    if (rnd() % 2 && n >= 2) { /* a consistent header for the batch after the links */
        size_t b = 2 + 2 * (out[1] % 8);
        if (n >= b + 40) {
            uint32_t length = (uint32_t)(n - b - 40), count = length / 24;
            memcpy(out + b, "DCUB", 4);
            out[b + 4] = 1;
            out[b + 5] &= 1;
            memset(out + b + 6, 0, 2);
            if (rnd() % 4) out[b + 5] = 0;
            for (int i = 0; i < 4; i++) out[b + 32 + i] = (uint8_t)(count >> (8 * i)), out[b + 36 + i] = (uint8_t)(length >> (8 * i));
        }
    }
    return n;
}

int main(int argc, char **argv) {
    if (argc < 3) {
        fprintf(stderr, "usage: fuzz_core SECONDS SEED...\n");
        return 2;
    }
    double seconds = atof(argv[1]);
    int n_seeds = argc - 2;
    uint8_t **seeds = malloc(n_seeds * sizeof *seeds);
    size_t *sizes = malloc(n_seeds * sizeof *sizes);
    for (int i = 0; i < n_seeds; i++)
        if (!(seeds[i] = read_file(argv[2 + i], &sizes[i]))) {
            fprintf(stderr, "fuzz_core: cannot read %s\n", argv[2 + i]);
            return 2;
        }
    rng_state ^= (uint64_t)time(NULL);
    long long runs = 0;
    size_t room = 1 << 17;
    uint8_t *buf = malloc(room);
    for (int i = 0; i < n_seeds; i++, runs++) { /* every seed once as it is */
        uint8_t *exact = malloc(sizes[i] ? sizes[i] : 1);
        memcpy(exact, seeds[i], sizes[i]);
        LLVMFuzzerTestOneInput(exact, sizes[i]);
        free(exact);
    }
    struct timespec t0, t;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (;; runs++) {
        if ((runs & 63) == 0) {
            clock_gettime(CLOCK_MONOTONIC, &t);
            if ((t.tv_sec - t0.tv_sec) + (t.tv_nsec - t0.tv_nsec) / 1e9 >= seconds) break;
        }
        int i = rnd() % n_seeds;
        size_t n = mutate(seeds[i], sizes[i], buf, room);
        uint8_t *exact = malloc(n ? n : 1); /* exactly n bytes: AddressSanitizer sees a read past them */
        memcpy(exact, buf, n);
        LLVMFuzzerTestOneInput(exact, n);
        free(exact);
    }
    for (int i = 0; i < n_seeds; i++) free(seeds[i]);
    free(seeds);
    free(sizes);
    free(buf);
    printf("fuzz_core: %lld inputs, %lld merged, %lld judged, %lld pushed, %lld summarized, %lld gathered, no finding\n",
           runs, reached_merge, reached_judge, reached_push, reached_stats, reached_series);
    fflush(stdout);
    return 0;
}
#endif
