/* The delay model of a set of frames: model.delays' chains and frame_delays, one frame at a time
 * (see that module for the definitions; tests/model/test_compiled_judge.py holds the two to one
 * another on real traces). Differences are taken as numpy takes them, wrapping in two's complement,
 * so that no input, however hostile, is undefined behaviour. */
#include <math.h>
#include <string.h>

#include "core.h"

static inline double diff(int64_t a, int64_t b) { return (double)(int64_t)((uint64_t)a - (uint64_t)b); }

/* One frame's chain: prev, passed, t_out filled; returns whether it is complete, *end where it ends. */
static int chain(const judge_t *j, int64_t r, const uint8_t *feeds, uint8_t *went_on, int64_t *end) {
    const int32_t s = j->s;
    const int64_t *in = j->enter + r * s, *ex = j->exit + r * s;
    int64_t *out = j->t_out + r * s, *prev = j->prev + r * s;
    uint8_t *passed = j->passed + r * s;
    const int64_t os = j->origin_stage[r];
    const int has_origin = os >= 0 && os < s; /* never out of range from a frame table: no input reads outside */
    memcpy(out, ex, (size_t)s * sizeof(int64_t));
    if (has_origin) out[os] = j->origin[r];
    int first = -1;
    for (int32_t k = 0; k < s; k++) {
        passed[k] = in[k] != MISSING || out[k] != MISSING;
        if (passed[k] && first < 0) first = k;
    }
    int reached, starts;
    int64_t e = MISSING;
    if (j->n_links == 0) {
        const int32_t last = s - 1;
        int32_t upto = -1;
        for (int32_t k = 0; k < s; k++) {
            prev[k] = upto;
            if (passed[k]) upto = k;
        }
        reached = s > 0 && in[last] != MISSING;
        e = s > 0 ? (out[last] != MISSING ? out[last] : in[last]) : MISSING;
        starts = first == os;
    } else {
        for (int32_t k = 0; k < s; k++) {
            prev[k] = -1;
            went_on[k] = !passed[k] || !feeds[k];
        }
        for (int32_t l = 0; l < j->n_links; l++) {
            int32_t a = j->links[2 * l], b = j->links[2 * l + 1];
            if (a < 0 || a >= s || b < 0 || b >= s || a == b) continue;
            if (passed[a] && a > prev[b]) prev[b] = a;
            if (passed[b]) went_on[a] = 1;
        }
        int any_end = 0, all_on = 1;
        for (int32_t k = 0; k < s; k++) {
            if (passed[k] && !feeds[k]) {
                any_end = 1;
                int64_t t = out[k] != MISSING ? out[k] : in[k];
                if (t > e) e = t;
            }
            all_on &= went_on[k];
        }
        reached = any_end && all_on;
        starts = prev[has_origin ? os : 0] == -1;
    }
    int broken = 0;
    for (int32_t k = 0; k < s && !broken; k++) {
        int needs_out = passed[k] && (j->n_links ? (feeds[k] || j->has_exit[k]) : (k < s - 1 || j->has_exit[k]));
        broken = (passed[k] && k != os && in[k] == MISSING) || (needs_out && out[k] == MISSING);
    }
    *end = e;
    return has_origin && starts && reached && !broken;
}

/* Every figure of frame_delays for j->n frames; returns how many are complete. */
int dcu_judge(judge_t *j) {
    const int32_t s = j->s;
    uint8_t *feeds = j->scratch, *went_on = j->scratch + s;
    memset(feeds, 0, (size_t)s);
    for (int32_t l = 0; l < j->n_links; l++) {
        int32_t a = j->links[2 * l], b = j->links[2 * l + 1];
        if (a >= 0 && a < s && b >= 0 && b < s && a != b) feeds[a] = 1;
    }
    int complete_n = 0;
    for (int64_t r = 0; r < j->n; r++) {
        int64_t e;
        int c = chain(j, r, feeds, went_on, &e);
        j->complete[r] = (uint8_t)c;
        j->end[r] = e;
        complete_n += c;
        j->frame[r] = c ? diff(e, j->origin[r]) : NAN;
        j->glass[r] = c && j->capture[r] != MISSING ? diff(e, j->capture[r]) : NAN;
        const int64_t *in = j->enter + r * s, *ex = j->exit + r * s, *rd = j->ready + r * s;
        const int64_t *out = j->t_out + r * s, *prev = j->prev + r * s;
        for (int32_t k = 0; k < s; k++) {
            const int64_t at = r * s + k;
            const int both = ex[k] != MISSING && in[k] != MISSING;
            j->delay[at] = both ? diff(ex[k], in[k]) : NAN;
            const int64_t before = out[prev[k] > 0 ? prev[k] : 0];
            j->gap[at] = prev[k] >= 0 && before != MISSING && in[k] != MISSING ? diff(in[k], before) : NAN;
            if (both && rd[k] != MISSING) {
                int64_t start = rd[k] > in[k] ? rd[k] : in[k];
                if (start > ex[k]) start = ex[k];
                j->service[at] = diff(ex[k], start);
                j->wait[at] = diff(start, in[k]);
            } else {
                j->service[at] = NAN;
                j->wait[at] = NAN;
            }
        }
    }
    return complete_n;
}

/* Rows of a run's open table (cells: row x s x CELLS, keys: source << KEY_SHIFT | frame) judged, each as
 * a FrameTable row of frame_table_from_cells: complete, end, and the columns the relay pushes
 * (relay.live.framepack.node_columns: ints of INT_ROWS(s) x k, floats of FLOAT_ROWS(s) x k, a column a
 * frame, the cursor row 0). work: 10 * s + 8 int64 of room. Returns how many are complete. */
int64_t dcu_judge_rows(const int64_t *cells, const int64_t *keys, const int64_t *rows, int64_t k, int32_t s,
                       const uint8_t *has_exit, const int32_t *links, int32_t n_links, uint8_t *complete, int64_t *end,
                       int64_t *ints, double *floats, int64_t *work) {
    int64_t *in = work, *ex = work + s, *rd = work + 2 * s, *out = work + 3 * s, *prev = work + 4 * s;
    double *fig = (double *)(work + 5 * s); /* delay, gap, service, wait: s each (8 bytes, as int64) */
    uint8_t *bytes = (uint8_t *)(work + 9 * s); /* passed, then the judge's scratch: 3 * s bytes */
    int64_t origin, ostage, capture, e;
    uint8_t c;
    double frame, glass;
    judge_t j = {.n = 1, .s = s, .origin = &origin, .origin_stage = &ostage, .capture = &capture, .enter = in,
                 .exit = ex, .ready = rd, .has_exit = has_exit, .links = links, .n_links = n_links, .t_out = out,
                 .prev = prev, .end = &e, .passed = bytes, .complete = &c, .delay = fig, .gap = fig + s,
                 .service = fig + 2 * s, .wait = fig + 3 * s, .frame = &frame, .glass = &glass, .scratch = bytes + s};
    int64_t n_complete = 0;
    for (int64_t i = 0; i < k; i++) {
        const int64_t *cell = cells + rows[i] * s * CELLS;
        ostage = -1;
        origin = capture = MISSING;
        for (int32_t t = 0; t < s; t++, cell += CELLS) {
            if (ostage < 0 && cell[ORIGIN] != MISSING) {
                ostage = t;
                origin = cell[ORIGIN];
                capture = cell[CAPTURE];
            }
            in[t] = cell[ENTER];
            ex[t] = cell[EXIT];
            rd[t] = cell[READY];
        }
        n_complete += dcu_judge(&j);
        complete[i] = c;
        end[i] = e;
        const int64_t key = keys[rows[i]];
        int64_t *col = ints + i;
        col[0] = 0;
        col[1 * k] = key >> KEY_SHIFT;
        col[2 * k] = key & ((1LL << KEY_SHIFT) - 1);
        col[3 * k] = origin;
        col[4 * k] = e;
        col[5 * k] = c;
        for (int32_t t = 0; t < s; t++) {
            col[(6 + t) * k] = in[t];
            col[(6 + s + t) * k] = ex[t];
        }
        col[(6 + 2 * s) * k] = capture;
        col[(7 + 2 * s) * k] = 0;
        col[(8 + 2 * s) * k] = 0;
        double *f = floats + i;
        f[0] = frame;
        f[k] = glass;
        for (int32_t q = 0; q < 4 * s; q++) f[(2 + q) * k] = fig[q];
    }
    return n_complete;
}
