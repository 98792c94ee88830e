/* The native core shared by dcuscope's pad probes (_fastprobe.c) and its GStreamer tracer
 * (_tracer.c): the event record, the ring, and recording one buffer at one tracepoint. */
#ifndef DCUPROBE_H
#define DCUPROBE_H

#include <gst/gst.h>
#include <stdatomic.h>
#include <stdint.h>
#include <time.h>

#define FRAMES_MEDIA_TYPE "timestamp/x-dcuscope-frames"
#define MAX_STAGES 256

/* Points and fact kinds: probes/events.py. */
enum { P_ORIGIN = 0, P_ENTER = 1, P_EXIT = 2, P_READY = 3, P_CAPTURE = 4, P_DROP = 5, P_FACT = 6 };
enum { FACT_THREAD = 1 };

typedef struct {
  int64_t ts;
  int64_t frame;
  int32_t source;
  int16_t stage;
  int8_t point;
  int8_t code;
} DcuEvent;

_Static_assert(sizeof(DcuEvent) == 24, "DcuEvent must match probes.events.EVENT_DTYPE");

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
/* The frames meta of buf: its structure, or NULL. */
const GstStructure *dcu_frames_structure(GstBuffer *buf);
/* Entry i of the meta's (source, frame) lists, n = their length. */
guint dcu_frames_count(const GstStructure *s);
void dcu_frames_get(const GstStructure *s, guint i, int64_t *source, int64_t *frame);
/* The origin (ns) of entry i, 0 when the meta has none. */
int64_t dcu_frames_origin(const GstStructure *s, guint i);
/* A frames structure as plugins/frames.py writes and reads it: lists source (int), frame and
 * origin (guint64), n entries; plain fields when n is 1. */
GstStructure *dcu_frames_new(guint n, const int64_t *sources, const int64_t *frames, const int64_t *origins);
/* A pad's last push returned now: the thread that pushes on it is free (service/wait). */
void dcu_note_push_returned(GstPad *pad);
/* A sink pad whose element has no chain-list function: GStreamer splits lists it receives and
 * chains each buffer again, so a list there must not be recorded as a whole. */
gboolean dcu_pad_splits_lists(GstPad *pad);
int64_t dcu_clock_ns(clockid_t clock);
/* The in-process tracer (_tracer.c): made once; `pre` registers its push/chain-pre hooks too. */
void dcu_in_process_tracer(gboolean pre);

#endif
