/* Delay series: gathered from frames' values (model.delays.series_of), and summarized
 * (model.delays.summarize): count, mean, the percentiles and the maximum of each, as numpy computes
 * them, to the last bit. The statistics the relay pushes every second for every
 * DCU shown are a few dozen series each (stages, gaps, their service and wait, frame, glass): numpy's
 * cost there is its calls', ~60 µs a series, where selecting a few ranks of a few hundred values takes
 * a few µs. Many series in one call, their values one after another. */
#include <math.h>
#include <stdint.h>

#include "core.h"

#define NS_PER_MS 1e6

static const double PERCENTILES[SUMMARY_PERCENTILES] = {50, 95, 99};

static inline double whole_ns(double ms) { return rint(ms * NS_PER_MS); }

static inline double as_is(double x) { return x; }

/* The sum of F(a[i]) as numpy's float64 sum adds (pairwise: blocks of up to 128 values over 8
 * accumulators, halves above), so that it is numpy's to the bit when it is not exact too (a sum past
 * 2^53 ns, 104 days) and the order of the adds matters. pairwise_ns sums whole ns of values in ms,
 * pairwise_plain the values as they are. */
#define PAIRWISE(NAME, F)                                                                    \
    static double NAME(const double *a, int64_t n) {                                          \
        if (n < 8) {                                                                          \
            double res = -0.0;                                                                \
            for (int64_t i = 0; i < n; i++) res += F(a[i]);                                   \
            return res;                                                                       \
        }                                                                                     \
        if (n <= 128) {                                                                       \
            double r[8];                                                                      \
            for (int j = 0; j < 8; j++) r[j] = F(a[j]);                                       \
            int64_t i = 8;                                                                    \
            for (; i < n - (n % 8); i += 8)                                                   \
                for (int j = 0; j < 8; j++) r[j] += F(a[i + j]);                              \
            double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));  \
            for (; i < n; i++) res += F(a[i]);                                                \
            return res;                                                                       \
        }                                                                                     \
        int64_t half = n / 2;                                                                 \
        half -= half % 8;                                                                     \
        return NAME(a, half) + NAME(a + half, n - half);                                      \
    }
PAIRWISE(pairwise_ns, whole_ns)
PAIRWISE(pairwise_plain, as_is)

/* numpy's np.rint(a * 1e6).sum(): its reduction starts from the identity. */
static inline double sum_ns(const double *a, int64_t n) { return 0.0 + pairwise_ns(a, n); }

static inline void swap(double *a, double *b) {
    double t = *a;
    *a = *b;
    *b = t;
}

static void sift(double *v, int64_t root, int64_t n) {
    for (int64_t child; (child = 2 * root + 1) < n; root = child) {
        if (child + 1 < n && v[child + 1] > v[child]) child++;
        if (!(v[child] > v[root])) return;
        swap(&v[root], &v[child]);
    }
}

/* v[0:n] sorted ascending in O(n log n) whatever its order: the fallback that keeps a selection linear
 * on input made to defeat its pivots. */
static void heapsort(double *v, int64_t n) {
    for (int64_t i = n / 2; i-- > 0;) sift(v, i, n);
    for (int64_t end = n; end-- > 1;) {
        swap(&v[0], &v[end]);
        sift(v, 0, end);
    }
}

/* v[lo:hi] (no NaN) reordered so that v[k] holds its (k - lo)th smallest value, those before it no
 * greater and those after it no smaller (numpy's partition). Quickselect with a median of three and a
 * partition without branches (which value goes where is data, not a jump to mispredict: ~3x faster on
 * delays, whose order is random); after 2 log2(n) rounds the rest is sorted, so that input made to
 * defeat the pivots costs O(n log n), never O(n^2). */
static void select_rank(double *v, int64_t lo, int64_t hi, int64_t k) {
    int budget = 8;
    for (int64_t n = hi - lo; n > 1; n >>= 1) budget += 2;
    while (hi - lo > 2) {
        if (budget-- == 0) {
            heapsort(v + lo, hi - lo);
            return;
        }
        int64_t mid = lo + (hi - lo) / 2;
        if (v[mid] < v[lo]) swap(&v[mid], &v[lo]);
        if (v[hi - 1] < v[lo]) swap(&v[hi - 1], &v[lo]);
        if (v[hi - 1] < v[mid]) swap(&v[hi - 1], &v[mid]);
        const double pivot = v[mid];
        swap(&v[mid], &v[hi - 1]);  /* the pivot out of the way, at the end; v[lo] <= pivot */
        /* Lomuto, branch-free: v[lo:j] < pivot, v[j:i] >= pivot */
        int64_t j = lo;
        for (int64_t i = lo; i < hi - 1; i++) {
            const double x = v[i];
            const int64_t less = x < pivot;
            v[i] = v[j];
            v[j] = x;
            j += less;
        }
        swap(&v[j], &v[hi - 1]);  /* the pivot at its rank j */
        if (k == j) return;
        if (k < j) {
            hi = j;
        } else if (v[lo] < pivot) {
            lo = j + 1;
        } else {
            /* The least value is the pivot's, perhaps many times: those equal to it would all go right
             * round after round; they are skipped at once. */
            int64_t e = j + 1;
            for (int64_t i = j + 1; i < hi; i++) {
                const double x = v[i];
                const int64_t same = x == pivot;
                v[i] = v[e];
                v[e] = x;
                e += same;
            }
            if (k < e) return;  /* equal to the pivot */
            lo = e;
        }
    }
    if (hi - lo == 2 && v[lo + 1] < v[lo]) swap(&v[lo], &v[lo + 1]);
}

/* The values at ranks lo and lo + 1 of v[0:n] (n > 0, no NaN) and the linear interpolation numpy's
 * percentile(method="linear") makes between them (model.delays.linear_percentiles), for each percentile,
 * ascending; v is reordered. */
static void percentiles(double *v, int64_t n, double *out) {
    int64_t from = 0;
    for (int p = 0; p < SUMMARY_PERCENTILES; p++) {
        const double virtual_ = (double)(n - 1) * (PERCENTILES[p] / 100);
        const double below = floor(virtual_), gamma = virtual_ - below;
        const int64_t lo = (int64_t)below, hi = lo + 1 < n ? lo + 1 : n - 1;
        /* Each rank selected among the values at or after the last one: those before it are no greater. */
        if (lo >= from) select_rank(v, from, n, lo);
        if (hi > lo) {  /* the next rank: the least value after lo */
            int64_t least = hi;
            for (int64_t i = hi + 1; i < n; i++)
                if (v[i] < v[least]) least = i;
            swap(&v[hi], &v[least]);
        }
        from = hi + 1;
        const double a = v[lo], b = v[hi], diff = b - a;
        out[p] = gamma >= 0.5 ? b - diff * (1 - gamma) : a + diff * gamma;
    }
}

/* k series, series i being values[offsets[i]:offsets[i + 1]] (ms), each summarized into out[i * SUMMARY
 * ...]: count, mean (of the values in whole ns, summed as numpy sums them), p50, p95, p99, max. A series
 * holding a NaN has NaN for all but its count, as numpy gives; an empty one NaN but its count 0. The
 * values are reordered in place. */
void dcu_summarize(double *values, const int64_t *offsets, int64_t k, double *out) {
    for (int64_t i = 0; i < k; i++) {
        double *v = values + offsets[i], *o = out + i * SUMMARY;
        const int64_t n = offsets[i + 1] - offsets[i];
        o[0] = (double)n;
        double top = -INFINITY;
        int nan = n == 0;
        for (int64_t j = 0; j < n; j++) {
            if (isnan(v[j])) nan = 1;
            if (v[j] > top) top = v[j];
        }
        const double total = sum_ns(v, n);  /* before the selection reorders them: numpy's order */
        if (nan) {
            for (int f = 1; f < SUMMARY; f++) o[f] = NAN;
            continue;
        }
        o[1] = total / (double)n / NS_PER_MS;
        percentiles(v, n, o + 2);
        o[SUMMARY - 1] = top;
    }
}

/* v[0:n] sorted ascending: quicksort with the partition above (no branch on the data), insertion sort
 * below 16 values, the heapsort past 2 log2(n) levels. */
static void sort_values(double *v, int64_t n) {
    int budget = 8;
    for (int64_t m = n; m > 1; m >>= 1) budget += 2;
    while (n > 16) {
        if (budget-- == 0) {
            heapsort(v, n);
            return;
        }
        int64_t mid = n / 2;
        if (v[mid] < v[0]) swap(&v[mid], &v[0]);
        if (v[n - 1] < v[0]) swap(&v[n - 1], &v[0]);
        if (v[n - 1] < v[mid]) swap(&v[n - 1], &v[mid]);
        const double pivot = v[mid];
        swap(&v[mid], &v[n - 1]);
        int64_t j = 0;
        for (int64_t i = 0; i < n - 1; i++) {
            const double x = v[i];
            const int64_t less = x < pivot;
            v[i] = v[j];
            v[j] = x;
            j += less;
        }
        swap(&v[j], &v[n - 1]);
        /* the smaller side by recursion, the larger by the loop: log2(n) frames deep at most */
        if (j < n - 1 - j) {
            sort_values(v, j);
            v += j + 1;
            n -= j + 1;
        } else {
            sort_values(v + j + 1, n - j - 1);
            n = j;
        }
    }
    for (int64_t i = 1; i < n; i++) {
        const double x = v[i];
        int64_t j = i;
        for (; j > 0 && v[j - 1] > x; j--) v[j] = v[j - 1];
        v[j] = x;
    }
}

/* The value of rank r (from 0) of the union of a[0:na] and b[0:nb], both ascending: i values of a and
 * r + 1 - i of b are the r + 1 least, for the least i that takes none of a too late. */
static double merged_rank(const double *a, int64_t na, const double *b, int64_t nb, int64_t r) {
    int64_t lo = r + 1 > nb ? r + 1 - nb : 0, hi = r + 1 < na ? r + 1 : na;
    while (lo < hi) {
        const int64_t i = lo + (hi - lo) / 2, j = r + 1 - i;
        if (j > 0 && a[i] < b[j - 1]) lo = i + 1;
        else hi = i;
    }
    const int64_t j = r + 1 - lo;
    const double x = lo > 0 ? a[lo - 1] : -INFINITY, y = j > 0 ? b[j - 1] : -INFINITY;
    return x > y ? x : y;
}

/* k whole-run series (relay.live.values.RunValues, exact and without NaN), summarized with the values of
 * frames not final yet, as summarize gives the union of both. Series i: its values held[i][0:n_held[i]],
 * ascending up to n_sorted[i], as they came after: those are sorted in (scratch: room for them); the
 * sum of their whole ns held_ns[i]; its open frames' values extra[eoff[i]:eoff[i + 1]] (reordered). */
void dcu_summarize_held(double *const *held, const int64_t *n_sorted, const int64_t *n_held, const double *held_ns,
                        double *extra, const int64_t *eoff, int64_t k, double *scratch, double *out) {
    for (int64_t i = 0; i < k; i++) {
        double *a = held[i], *b = extra + eoff[i], *o = out + i * SUMMARY;
        const int64_t sorted = n_sorted[i], na = n_held[i], nb = eoff[i + 1] - eoff[i], m = na - sorted;
        if (m > 0) {  /* the new values sorted, then merged in from the end */
            for (int64_t t = 0; t < m; t++) scratch[t] = a[sorted + t];
            sort_values(scratch, m);
            int64_t p = sorted - 1, q = m - 1, w = na - 1;
            while (q >= 0) a[w--] = p >= 0 && a[p] > scratch[q] ? a[p--] : scratch[q--];
        }
        const double total = sum_ns(b, nb);  /* in their order, as numpy sums them */
        sort_values(b, nb);
        const int64_t n = na + nb;
        o[0] = (double)n;
        if (n == 0) {
            for (int f = 1; f < SUMMARY; f++) o[f] = NAN;
            continue;
        }
        o[1] = (held_ns[i] + total) / (double)n / NS_PER_MS;
        for (int p = 0; p < SUMMARY_PERCENTILES; p++) {
            const double virtual_ = (double)(n - 1) * (PERCENTILES[p] / 100);
            const double below = floor(virtual_), gamma = virtual_ - below;
            const int64_t lo = (int64_t)below, hi = lo + 1 < n ? lo + 1 : n - 1;
            const double x = merged_rank(a, na, b, nb, lo), y = merged_rank(a, na, b, nb, hi), diff = y - x;
            o[2 + p] = gamma >= 0.5 ? y - diff * (1 - gamma) : x + diff * gamma;
        }
        const double top_a = na ? a[na - 1] : -INFINITY, top_b = nb ? b[nb - 1] : -INFINITY;
        o[SUMMARY - 1] = top_a > top_b ? top_a : top_b;
    }
}

/* The series of n frames' values (model.delays.series_of), gathered one after another into out (room for
 * n * (4 s + 1) values) in the order series_of makes them: the glass-to-glass delays that are not NaN;
 * then for each stage b with an exit (has_exit[b]): its delays that are not NaN, and where it has
 * service times, those and the wait times of the same frames; then the gaps, stage b after stage b,
 * each split by the previous stage a the frame passed (a ascending). Every series keeps the frames' row
 * order. A row of rows (room for 1 + 3 s + s * s) says what each series is: (kind, a, b, count), its
 * values following the last's. busy[b]: the service times of the frames first in their output buffer
 * at b summed as numpy sums them (NaN without service times). delay, gap, service and wait are (n, s),
 * row-major; prev (n, s); first (n, s) 0 or 1; pairs (s * s) and scratch (n) are work space. A gap whose
 * previous stage is out of range (never, from the judge) is counted nowhere. Returns the rows made. */
int64_t dcu_series(int64_t n, int32_t s, const double *delay, const double *gap, const double *service,
                   const double *wait, const double *glass, const int64_t *prev, const uint8_t *first,
                   const uint8_t *has_exit, double *out, int64_t *rows, double *busy, int64_t *pairs,
                   double *scratch) {
    int64_t at = 0, k = 0;
#define ROW(KIND, A, B, COUNT) \
    do { rows[4 * k] = (KIND); rows[4 * k + 1] = (A); rows[4 * k + 2] = (B); rows[4 * k + 3] = (COUNT); k++; } while (0)
    int64_t start = at;
    for (int64_t i = 0; i < n; i++)
        if (!isnan(glass[i])) out[at++] = glass[i];
    ROW(SERIES_GLASS, -1, -1, at - start);
    for (int32_t b = 0; b < s; b++) {
        busy[b] = NAN;
        if (!has_exit[b]) continue;
        start = at;
        for (int64_t i = 0; i < n; i++)
            if (!isnan(delay[i * s + b])) out[at++] = delay[i * s + b];
        ROW(SERIES_STAGE, b, b, at - start);
        int64_t timed = 0, firsts = 0;
        for (int64_t i = 0; i < n; i++) {
            const double v = service[i * s + b];
            if (isnan(v)) continue;
            out[at + timed++] = v;
            if (first[i * s + b]) scratch[firsts++] = v;
        }
        if (!timed) continue;
        ROW(SERIES_SERVICE, b, b, timed);
        at += timed;
        for (int64_t i = 0; i < n; i++)
            if (!isnan(service[i * s + b])) out[at++] = wait[i * s + b];
        ROW(SERIES_WAIT, b, b, timed);
        busy[b] = 0.0 + pairwise_plain(scratch, firsts);
    }
    /* The gaps: counted per (a, b), their places given in series_of's order, then written in row order. */
    for (int64_t p = 0; p < (int64_t)s * s; p++) pairs[p] = 0;
    for (int64_t i = 0; i < n; i++)
        for (int32_t b = 0; b < s; b++) {
            const int64_t a = prev[i * s + b];
            if (!isnan(gap[i * s + b]) && 0 <= a && a < s) pairs[a * s + b]++;
        }
    for (int32_t b = 0; b < s; b++)
        for (int32_t a = 0; a < s; a++) {
            const int64_t count = pairs[(int64_t)a * s + b];
            if (!count) continue;
            ROW(SERIES_GAP, a, b, count);
            pairs[(int64_t)a * s + b] = at;
            at += count;
        }
    for (int64_t i = 0; i < n; i++)
        for (int32_t b = 0; b < s; b++) {
            const int64_t a = prev[i * s + b];
            if (!isnan(gap[i * s + b]) && 0 <= a && a < s) out[pairs[a * s + b]++] = gap[i * s + b];
        }
#undef ROW
    return k;
}
