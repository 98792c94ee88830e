/* The event record, the ring, and recording one buffer at one tracepoint (ring.c): what every
 * tracepoint of the native library writes through, pad probes (padprobe.c) and the GStreamer
 * tracer's hooks (tracer.c) alike. Above frames.h only. */
#ifndef DCU_RING_H
#define DCU_RING_H

#include <gst/gst.h>
#include <stdatomic.h>
#include <stdint.h>
#include <time.h>

#include "frames.h"

#define MAX_STAGES 256

/* Points and fact kinds: dcuscope/protocol/events.py. */
enum { P_ORIGIN = 0, P_ENTER = 1, P_EXIT = 2, P_READY = 3, P_CAPTURE = 4, P_DROP = 5, P_FACT = 6, P_LINK = 7, P_KEY = 8 };
enum { FACT_THREAD = 1 };

typedef struct {
  int64_t ts;
  int64_t frame;
  int32_t source;
  int16_t stage;
  int8_t point;
  int8_t code;
} DcuEvent;

_Static_assert(sizeof(DcuEvent) == 24, "DcuEvent must match protocol.events.EVENT_DTYPE");

typedef struct DcuRing DcuRing;
typedef struct DcuStageEnters DcuStageEnters;
typedef struct DcuPadState DcuPadState;

/* One tracepoint: which ring, which clock, which stage and point. */
typedef struct {
  DcuRing *ring;
  clockid_t clock;
  int16_t stage;
  int8_t point;
  DcuStageEnters *enters; /* the stage's table of recent enters (enter and exit points) */
  DcuPadState *pad_state; /* exit points only: when the pad's last push returned */
} DcuProbe;

DcuRing *dcu_ring_new(uint64_t capacity_events);
void dcu_ring_free(DcuRing *ring);
uint64_t dcu_drain(DcuRing *ring, void *out, uint64_t max_events);
void dcu_stats(DcuRing *ring, uint64_t *written, uint64_t *dropped, uint64_t *unidentified);
uint64_t dcu_push(DcuRing *ring, const void *events, uint64_t n);

/* Fill p for a tracepoint on pad (takes a reference on the ring; dcu_probe_clear drops it). */
void dcu_probe_setup(DcuProbe *p, DcuRing *ring, GstPad *pad, int stage, int point, clockid_t clock);
void dcu_probe_clear(DcuProbe *p);
/* Record the frames buf carries (its frames meta) at p, all at ts; counts it unidentified if none. */
void dcu_record_buffer(DcuProbe *p, GstBuffer *buf, int64_t ts);
/* The same for frames listed in s (a frames structure: source and frame lists) that buf carries. */
void dcu_record_frames(DcuProbe *p, const GstStructure *s, GstBuffer *buf, int64_t ts);
/* A pad's last push returned now: the thread that pushes on it is free (service/wait). */
void dcu_note_push_returned(GstPad *pad);
/* A sink pad whose element has no chain-list function: GStreamer splits lists it receives and
 * chains each buffer again, so a list there must not be recorded as a whole. */
gboolean dcu_pad_splits_lists(GstPad *pad);
int64_t dcu_clock_ns(clockid_t clock);
/* The library's version of this layout (probes/capture/native.py checks both). */
int dcu_abi_version(void);
int dcu_event_size(void);
uint64_t dcu_ring_capacity(DcuRing *ring);
/* The clock the probes read, for callers that want to compare (tests, headers). */
int64_t dcu_now(int clock_id);
/* How many push-post hooks ran (all pads of the process): for benchmarks. */
uint64_t dcu_hook_calls(void);

#endif
