/* dcuscope's compiled core: what the relay's live path does per event, in C (dcuscope.model.compiled
 * loads it). Three modules, bottom-up:
 *   batch.c  a wire batch decoded and its events checked (protocol.wire's decode_batch, check_events);
 *   merge.c  events paired into the open frames of a run (relay.live.run.LiveRun's merge), and their
 *            origins counted per source and time bin (the run's accounting and window);
 *   judge.c  the delay model of a set of frames (model.delays' chains and frame_delays);
 *   push.c   the columns a push carries, moved to the relay's clock (relay.live.framepack);
 *   stats.c  delay series gathered from frames' values (model.delays.series_of) and summarized
 *            (model.delays.summarize: count, mean, percentiles, max).
 * Python keeps numpy versions of all as the reference (tests hold them to one another).
 * No GStreamer and no Python: any C compiler builds it. Every entry point takes its sizes and never
 * reads or writes outside the arrays they describe, whatever the input (tests/model/fuzz). */
#ifndef DCU_CORE_H
#define DCU_CORE_H

#include <stdint.h>

#define CORE_ABI 7
#define MISSING (-1)
#define CELLS 6
#define ORIGIN 0
#define ENTER 1
#define EXIT 2
#define READY 3
#define CAPTURE 4
#define GROUP 5
#define FRAME_POINTS 5
#define KEY_SHIFT 44

#pragma pack(push, 1)
typedef struct { int64_t ts, frame; int32_t source; int16_t stage; int8_t point, code; } event_t;
#pragma pack(pop)

static inline uint64_t mix(uint64_t k) {
    k ^= k >> 33;
    k *= 0xff51afd7ed558ccdULL;
    k ^= k >> 33;
    return k;
}

/* batch.c */
int dcu_core_abi(void);
int dcu_event_size(void);
int64_t dcu_check(const event_t *ev, int64_t n, int32_t n_stages, const uint8_t *codes, int64_t source_limit,
                  int64_t frame_limit);
int dcu_decode_batch(const uint8_t *data, int64_t len, int32_t n_stages, int64_t max_events, const uint8_t *codes,
                     int64_t source_limit, int64_t frame_limit, int64_t *out);

/* merge.c */
int64_t dcu_unknown_source(const char *sources, int64_t n, int64_t stride, const int64_t *src_ids, int64_t n_src);
void dcu_merge_rehash(const int64_t *okey, int64_t n, int64_t *hkey, int64_t *hrow, int64_t mask);
void dcu_merge_locate(const int64_t *keys, int64_t n, const int64_t *hkey, const int64_t *hrow, int64_t mask,
                      int64_t *rows_out, uint8_t *found_out);
int64_t dcu_merge(const event_t *ev, int64_t n, int32_t n_stages, int64_t *hkey, int64_t *hrow, int64_t mask,
                  int64_t *okey, int64_t *cells, int64_t *last, uint8_t *shown, int64_t *end, int64_t rows,
                  int64_t rows_cap, const int64_t *src_ids, const int64_t *watermark, int64_t n_src,
                  uint8_t *has_exit, int64_t *io);
int64_t dcu_origins(const event_t *ev, int64_t n, int64_t bin_ns, int64_t *source, int64_t *bin, int64_t *count,
                    int64_t *hkey, int64_t *hrow, int64_t mask, int64_t *top);

/* judge.c */
typedef struct {
    /* in: n frames of s stages (arrays of n, or n x s frame-major) */
    int64_t n;
    int32_t s;
    const int64_t *origin, *origin_stage, *capture, *enter, *exit, *ready;
    const uint8_t *has_exit;            /* s */
    const int32_t *links;               /* n_links pairs (a, b): stage a feeds stage b; none: one chain */
    int32_t n_links;
    /* out */
    int64_t *t_out, *prev, *end;
    uint8_t *passed, *complete;
    double *delay, *gap, *service, *wait; /* n x s */
    double *frame, *glass;                /* n */
    uint8_t *scratch;                   /* 2 * s bytes of room */
} judge_t;

int dcu_judge(judge_t *j);
int64_t dcu_judge_rows(const int64_t *cells, const int64_t *keys, const int64_t *rows, int64_t k, int32_t s,
                       const uint8_t *has_exit, const int32_t *links, int32_t n_links, uint8_t *complete, int64_t *end,
                       int64_t *ints, double *floats, int64_t *work);

/* push.c: the pushed columns (relay.live.framepack) */
#define INT_ROWS(s) (9 + 2 * (int64_t)(s))
#define FLOAT_ROWS(s) (2 + 4 * (int64_t)(s))
void dcu_push_columns(const int64_t *ints, const double *floats, int64_t k, int32_t s, const int64_t *from,
                      const int64_t *ref, const int64_t *offset, const double *drift, const int64_t *unc,
                      const double *growth, int64_t n_seg, int64_t base_unc, int64_t *ints_out, double *floats_out);

/* stats.c: delay series gathered (model.delays.series_of) and summarized (model.delays.summarize) */
#define SUMMARY 6              /* count, mean, p50, p95, p99, max */
#define SUMMARY_PERCENTILES 3
void dcu_summarize(double *values, const int64_t *offsets, int64_t k, double *out);
void dcu_summarize_held(double *const *held, const int64_t *n_sorted, const int64_t *n_held, const double *held_ns,
                        double *extra, const int64_t *eoff, int64_t k, double *scratch, double *out);
enum { SERIES_GLASS, SERIES_STAGE, SERIES_SERVICE, SERIES_WAIT, SERIES_GAP };  /* a gathered series' kind */
int64_t dcu_series(int64_t n, int32_t s, const double *delay, const double *gap, const double *service,
                   const double *wait, const double *glass, const int64_t *prev, const uint8_t *first,
                   const uint8_t *has_exit, double *out, int64_t *rows, double *busy, int64_t *pairs,
                   double *scratch);

#endif
