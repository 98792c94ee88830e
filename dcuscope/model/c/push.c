/* The columns a push carries (relay.live.framepack.corrected): a run's shown frames, kept as the node's
 * clock has them, moved to the relay's clock and laid out field after field, with the clock rows set and
 * the figures in ms. One pass over frames kept a frame a row (frame-major, as the engine keeps them). */
#include <math.h>
#include <stdint.h>

#include "core.h"

#define NS_PER_MS 1e6

/* A double as numpy's astype(int64) gives it on x86-64 (out of range and NaN: INT64_MIN), never undefined. */
static inline int64_t to_i64(double v) {
    return v > -9.2233720368547758e18 && v < 9.2233720368547758e18 ? (int64_t)v : INT64_MIN;
}

static inline int64_t sub(int64_t a, int64_t b) { return (int64_t)((uint64_t)a - (uint64_t)b); }

static inline int64_t add(int64_t a, int64_t b) { return (int64_t)((uint64_t)a + (uint64_t)b); }

/* k frames of ints (k x INT_ROWS(s)) and floats (k x FLOAT_ROWS(s)), frame-major, into ints_out and
 * floats_out, field-major (INT_ROWS(s) x k, FLOAT_ROWS(s) x k). The segments of the run's correction
 * (n_seg, sorted by from; none: nothing moved, every bound base_unc) as relay.clock.correction.Correction
 * keeps them: the one in force at a frame's origin moves all its times. */
void dcu_push_columns(const int64_t *ints, const double *floats, int64_t k, int32_t s, const int64_t *from,
                      const int64_t *ref, const int64_t *offset, const double *drift, const int64_t *unc,
                      const double *growth, int64_t n_seg, int64_t base_unc, int64_t *ints_out, double *floats_out) {
    const int64_t ir = INT_ROWS(s), fr = FLOAT_ROWS(s), times_end = 6 + 2 * (int64_t)s;
    for (int64_t i = 0; i < k; i++) {
        const int64_t *in = ints + i * ir;
        const int64_t origin = in[3];
        int64_t off = 0, r0 = 0, u = base_unc;
        double d = 0, g = 0;
        if (n_seg > 0) {
            int64_t lo = 0, hi = n_seg; /* searchsorted(from, origin, side="right") - 1, at least 0 */
            while (lo < hi) {
                int64_t mid = lo + (hi - lo) / 2;
                if (from[mid] <= origin) lo = mid + 1; else hi = mid;
            }
            int64_t seg = lo > 0 ? lo - 1 : 0;
            off = offset[seg], r0 = ref[seg], d = drift[seg], g = growth[seg], u = add(unc[seg], base_unc);
        }
        int64_t moved_origin = origin;
        for (int64_t r = 0; r < ir; r++) {
            int64_t v = in[r];
            if (r >= 3 && r < times_end && r != 5 && v != MISSING) {
                v = sub(v, add(off, to_i64(rint(d * (double)sub(v, r0) / 1e9))));
                if (r == 3) moved_origin = v;
            }
            ints_out[r * k + i] = v;
        }
        int64_t from_ref = sub(origin, r0);
        from_ref = from_ref < 0 ? sub(0, from_ref) : from_ref; /* numpy's abs: INT64_MIN stays */
        ints_out[(7 + 2 * s) * k + i] = sub(origin, moved_origin);
        ints_out[(8 + 2 * s) * k + i] = add(u, to_i64(ceil(g * (double)from_ref / 1e9)));
        const double *f = floats + i * fr;
        const int64_t end_off = add(off, to_i64(rint(d * (double)sub(in[4], r0) / 1e9)));
        for (int64_t q = 0; q < fr; q++)
            floats_out[q * k + i] = (q == 1 ? f[q] - (double)end_off : f[q]) / NS_PER_MS;
    }
}
