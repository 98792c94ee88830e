/* The event ring, and recording one buffer at one tracepoint (ring.h).
 *
 * A Python pad probe costs 15-60 us per call (PyGObject marshalling, GIL); a native tracepoint
 * reads the clock, finds the frame-identity meta and copies a few integers into a ring, without
 * ever touching Python or blocking a streaming thread. What fires it is a pad probe (padprobe.c)
 * or the dcuscope tracer's hooks (tracer.c); both record through dcu_record_buffer.
 *
 * Ring: a bounded multi-producer / single-consumer queue of 24-byte records laid out exactly
 * like protocol.events.EVENT_DTYPE. Producers (any number of streaming threads) reserve slots
 * with one compare-and-swap per buffer (Vyukov's bounded queue, slots reserved in runs);
 * the one consumer (the Python shipping thread, or the trace writer's thread) copies records out
 * with dcu_drain. When the ring is full a producer counts the events as dropped and returns: it
 * never waits.
 *
 * Frame identity: the frames meta (frames.h), one entry per frame the buffer holds. A batch or a
 * collage thus yields one record per frame, all with the single timestamp read for the buffer.
 *
 * Service and wait (format 2): the dcuscope tracer hooks pad-push-post and pad-push-list-post
 * (in-process, no GST_TRACERS needed) and calls dcu_note_push_returned: the pad's state notes the
 * time, the thread that pushes on it is free again. At the next exit on that pad the recording
 * writes, per frame, a "ready" record: the later of that time and the last enter (at this stage)
 * of the frames the buffer holds, which a per-stage table of recent enters gives. Work on the
 * buffer cannot have started before ready, so service = exit - ready and wait = ready - enter
 * (dcuscope/model/delays.py). Where the frames came in on another thread than the one that pushes
 * them out (queue, aggregator), ready is also no earlier than exit minus the CPU time the pushing
 * thread used since its last push returned (CLOCK_THREAD_CPUTIME_ID): waking up is not work. A
 * "thread" fact tells which streaming thread pushes a stage's output, when it changes.
 *
 * Capture (format 2): an origin buffer that carries the sender's capture time (a reference
 * timestamp meta "timestamp/x-ntp", which rtpjitterbuffer attaches from RTCP sender reports)
 * also yields a "capture" record with that time on the Unix epoch.
 */

#include "ring.h"

#include <stdlib.h>
#include <string.h>

#define DCU_ABI_VERSION 2
#define NTP_MEDIA_TYPE "timestamp/x-ntp"
#define NTP_TO_UNIX_NS (2208988800LL * 1000000000LL)
#define ENTER_SETS 256 /* recent enters remembered per stage: 256 sets of 4 slots */
#define ENTER_WAYS 4
#define MAX_GROUP 127

/* The last enter of recent frames at one stage, by frame key: written by enter probes, read by
 * exit probes. 4-way sets: a frame's enter is lost only when four frames of its set entered
 * after it and it has still not left. A slot is (key, ts); a reader checks the key before and
 * after reading ts, so a slot overwritten meanwhile reads as absent, never as another frame's
 * time. Two enter probes of one stage racing for one slot may lose one of the two frames. */
typedef struct {
  _Atomic uint64_t key;
  _Atomic int64_t ts;
  _Atomic int thread; /* the thread that brought the frame in */
} DcuEnterSlot;

struct DcuStageEnters {
  DcuEnterSlot slots[ENTER_SETS][ENTER_WAYS];
};

/* One slot: the record plus its sequence number (Vyukov). seq == pos: free for the producer
 * of position pos; seq == pos + 1: filled, readable by the consumer. */
typedef struct {
  _Atomic uint64_t seq;
  DcuEvent ev;
} DcuCell;

struct DcuRing {
  DcuCell *cells;
  uint64_t mask;
  /* Producers contend on enqueue_pos only; keep the consumer's fields on another line so
   * draining does not bounce the producers' cache line. */
  _Alignas(64) _Atomic uint64_t enqueue_pos;
  _Alignas(64) uint64_t dequeue_pos;
  _Atomic uint64_t dropped;
  _Atomic uint64_t unidentified;
  _Atomic int refcount;
  DcuStageEnters *_Atomic enters[MAX_STAGES];
};

/* Per traced src pad (object data of the pad, freed with it): when its last push returned,
 * and which thread pushed last. */
struct DcuPadState {
  _Atomic int64_t last_post;
  _Atomic int64_t cpu_at_post; /* CPU time of the pushing thread when its last push returned */
  _Atomic int post_thread;     /* ...and which thread that was */
  _Atomic int last_thread;
  _Atomic int wants_cpu;       /* frames reach this pad on another thread than they entered on */
  clockid_t clock;
};

/* Interned once: comparing quarks is an integer compare, where matching the caps with
 * gst_caps_is_subset for every buffer would walk structures. */
static GQuark ntp_quark, pad_state_quark;
/* What a sink pad does with a buffer list when its element has no chain-list function: it
 * splits the list and chains (and probes) each buffer again. */
static GstPadChainListFunction default_chain_list;
static gsize init_done = 0;

static void init_once(void) {
  if (g_once_init_enter(&init_done)) {
    dcu_frames_init();
    ntp_quark = g_quark_from_static_string(NTP_MEDIA_TYPE);
    pad_state_quark = g_quark_from_static_string("dcuscope-pad-state");
    GstPad *dummy = gst_pad_new("dcu-probe-dummy", GST_PAD_SINK);
    default_chain_list = GST_PAD_CHAINLISTFUNC(dummy);
    gst_object_unref(dummy);
    g_once_init_leave(&init_done, 1);
  }
}

int dcu_abi_version(void) { return DCU_ABI_VERSION; }

int dcu_event_size(void) { return (int)sizeof(DcuEvent); }

static uint64_t round_up_pow2(uint64_t n) {
  uint64_t p = 2;
  while (p < n) p <<= 1;
  return p;
}

/* A ring of at least capacity_events records (rounded up to a power of two). */
DcuRing *dcu_ring_new(uint64_t capacity_events) {
  init_once();
  if (capacity_events < 2) capacity_events = 2;
  uint64_t cap = round_up_pow2(capacity_events);
  DcuRing *ring = aligned_alloc(64, sizeof(DcuRing));
  if (!ring) return NULL;
  memset(ring, 0, sizeof(*ring));
  ring->cells = calloc(cap, sizeof(DcuCell));
  if (!ring->cells) {
    free(ring);
    return NULL;
  }
  for (uint64_t i = 0; i < cap; i++) atomic_init(&ring->cells[i].seq, i);
  ring->mask = cap - 1;
  atomic_init(&ring->refcount, 1);
  return ring;
}

uint64_t dcu_ring_capacity(DcuRing *ring) { return ring->mask + 1; }

static void ring_unref(DcuRing *ring) {
  if (atomic_fetch_sub_explicit(&ring->refcount, 1, memory_order_acq_rel) == 1) {
    for (int i = 0; i < MAX_STAGES; i++) free(atomic_load(&ring->enters[i]));
    free(ring->cells);
    free(ring);
  }
}

/* Release the caller's reference; probes still attached keep the ring alive until removed. */
void dcu_ring_free(DcuRing *ring) {
  if (ring) ring_unref(ring);
}

/* Reserve n consecutive positions, or return FALSE when the ring is full. */
static gboolean ring_reserve(DcuRing *ring, uint64_t n, uint64_t *out_pos) {
  if (n > ring->mask + 1) return FALSE;
  uint64_t pos = atomic_load_explicit(&ring->enqueue_pos, memory_order_relaxed);
  for (;;) {
    /* The consumer frees slots in order, so the last slot of the run being free means the
     * whole run is free. */
    uint64_t last = pos + n - 1;
    uint64_t seq = atomic_load_explicit(&ring->cells[last & ring->mask].seq, memory_order_acquire);
    int64_t diff = (int64_t)(seq - last);
    if (diff == 0) {
      if (atomic_compare_exchange_weak_explicit(&ring->enqueue_pos, &pos, pos + n,
                                                memory_order_relaxed, memory_order_relaxed)) {
        *out_pos = pos;
        return TRUE;
      }
      /* pos was reloaded by the failed CAS */
    } else if (diff < 0) {
      return FALSE;
    } else {
      pos = atomic_load_explicit(&ring->enqueue_pos, memory_order_relaxed);
    }
  }
}

static inline void ring_publish(DcuRing *ring, uint64_t pos, const DcuEvent *ev) {
  DcuCell *cell = &ring->cells[pos & ring->mask];
  cell->ev = *ev;
  atomic_store_explicit(&cell->seq, pos + 1, memory_order_release);
}

/* Copy out up to max_events records, oldest first. Single consumer: callers serialise. */
uint64_t dcu_drain(DcuRing *ring, void *out, uint64_t max_events) {
  DcuEvent *dst = out;
  uint64_t pos = ring->dequeue_pos, n = 0;
  while (n < max_events) {
    DcuCell *cell = &ring->cells[pos & ring->mask];
    uint64_t seq = atomic_load_explicit(&cell->seq, memory_order_acquire);
    /* Not yet published (empty, or a producer between reserve and publish): stop here, the
     * rest comes with the next drain. */
    if (seq != pos + 1) break;
    dst[n++] = cell->ev;
    atomic_store_explicit(&cell->seq, pos + ring->mask + 1, memory_order_release);
    pos++;
  }
  ring->dequeue_pos = pos;
  return n;
}

/* written: events accepted (some may still sit in the ring); dropped: events lost because the
 * ring was full; unidentified: buffers that carried no frame identity. Any pointer may be NULL. */
void dcu_stats(DcuRing *ring, uint64_t *written, uint64_t *dropped, uint64_t *unidentified) {
  if (written) *written = atomic_load(&ring->enqueue_pos);
  if (dropped) *dropped = atomic_load(&ring->dropped);
  if (unidentified) *unidentified = atomic_load(&ring->unidentified);
}

static inline uint64_t frame_key(int64_t source, int64_t frame) {
  /* +1: key 0 marks an empty slot. */
  return (((uint64_t)source << 40) | ((uint64_t)frame & ((1ULL << 40) - 1))) + 1;
}

static inline DcuEnterSlot *enter_set(DcuStageEnters *t, uint64_t key) {
  return t->slots[(key * 0x9E3779B97F4A7C15ULL) >> 56]; /* Fibonacci hash, 8 bits */
}

/* Where to write key: its own slot, else an empty one, else the oldest of the set (the frame
 * most likely gone already). */
static DcuEnterSlot *slot_for(DcuStageEnters *t, uint64_t key) {
  DcuEnterSlot *set = enter_set(t, key), *oldest = &set[0];
  for (int w = 0; w < ENTER_WAYS; w++) {
    uint64_t k = atomic_load_explicit(&set[w].key, memory_order_relaxed);
    if (k == key || k == 0) return &set[w];
    if (atomic_load_explicit(&set[w].ts, memory_order_relaxed) < atomic_load_explicit(&oldest->ts, memory_order_relaxed))
      oldest = &set[w];
  }
  return oldest;
}

static void remember_enter(DcuStageEnters *t, uint64_t key, int64_t ts, int thread) {
  DcuEnterSlot *slot = slot_for(t, key);
  atomic_store_explicit(&slot->key, 0, memory_order_relaxed);
  atomic_thread_fence(memory_order_release);
  atomic_store_explicit(&slot->ts, ts, memory_order_relaxed);
  atomic_store_explicit(&slot->thread, thread, memory_order_relaxed);
  atomic_store_explicit(&slot->key, key, memory_order_release);
}

/* The enter time of the frame (0 if forgotten) and the thread that brought it in. */
static int64_t recall_enter(DcuStageEnters *t, uint64_t key, int *thread) {
  DcuEnterSlot *set = enter_set(t, key);
  for (int w = 0; w < ENTER_WAYS; w++) {
    DcuEnterSlot *slot = &set[w];
    if (atomic_load_explicit(&slot->key, memory_order_acquire) != key) continue;
    int64_t ts = atomic_load_explicit(&slot->ts, memory_order_relaxed);
    *thread = atomic_load_explicit(&slot->thread, memory_order_relaxed);
    atomic_thread_fence(memory_order_acquire);
    if (atomic_load_explicit(&slot->key, memory_order_relaxed) == key) return ts;
  }
  return 0;
}

static inline int64_t thread_cpu_ns(void) {
  struct timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
}

/* A small number for the calling thread, the same for its whole life. */
static _Atomic int next_thread_number = 1;
static __thread int thread_number = 0;

static inline int this_thread(void) {
  if (thread_number == 0) thread_number = atomic_fetch_add(&next_thread_number, 1);
  return thread_number;
}

static int64_t ntp_capture_ns(GstBuffer *buf) {
  gpointer state = NULL;
  GstMeta *meta;
  while ((meta = gst_buffer_iterate_meta_filtered(buf, &state, GST_REFERENCE_TIMESTAMP_META_API_TYPE))) {
    GstReferenceTimestampMeta *ref = (GstReferenceTimestampMeta *)meta;
    if (ref->reference && gst_caps_get_size(ref->reference) > 0 &&
        gst_structure_get_name_id(gst_caps_get_structure(ref->reference, 0)) == ntp_quark &&
        ref->timestamp > (guint64)NTP_TO_UNIX_NS)
      return (int64_t)ref->timestamp - NTP_TO_UNIX_NS;
  }
  return 0;
}

void dcu_record_buffer(DcuProbe *p, GstBuffer *buf, int64_t ts) {
  dcu_record_frames(p, dcu_frames_structure(buf), buf, ts);
}

void dcu_record_frames(DcuProbe *p, const GstStructure *s, GstBuffer *buf, int64_t ts) {
  DcuRing *ring = p->ring;
  const GValue *sources = s ? gst_structure_id_get_value(s, dcu_source_quark) : NULL;
  const GValue *frames = s ? gst_structure_id_get_value(s, dcu_frame_quark) : NULL;
  guint n = (sources && frames) ? MIN(dcu_field_size(sources), dcu_field_size(frames)) : 0;
  if (n == 0) {
    atomic_fetch_add_explicit(&ring->unidentified, 1, memory_order_relaxed);
    return;
  }
  int64_t ready = 0, capture = 0;
  guint per_frame = 1;
  int thread = 0;
  if (p->point == P_EXIT && p->pad_state) {
    /* The later of "the pushing thread came back from its last push" and the last enter. */
    DcuPadState *st = p->pad_state;
    ready = atomic_load_explicit(&st->last_post, memory_order_relaxed);
    thread = this_thread();
    gboolean handed_over = FALSE;
    for (guint i = 0; i < n; i++) {
      int64_t source = -1, frame = -1;
      int came_on = 0;
      dcu_value_i64(dcu_field_item(sources, i), &source);
      dcu_value_i64(dcu_field_item(frames, i), &frame);
      int64_t entered = recall_enter(p->enters, frame_key(source, frame), &came_on);
      if (entered > ready) ready = entered;
      if (entered > 0 && came_on != thread) handed_over = TRUE;
    }
    /* A stage that hands frames to a thread of its own (a queue, an aggregator's src thread)
     * works only while that thread runs: its work on this buffer is at most the CPU time the
     * thread spent since its last push returned. Waking up, or sleeping on a batch timeout,
     * is waiting. */
    if (handed_over && !atomic_load_explicit(&st->wants_cpu, memory_order_relaxed))
      atomic_store_explicit(&st->wants_cpu, 1, memory_order_relaxed);
    if (handed_over && ready > 0 && atomic_load_explicit(&st->post_thread, memory_order_relaxed) == thread) {
      int64_t since = atomic_load_explicit(&st->cpu_at_post, memory_order_relaxed);
      int64_t busy_from = ts - (thread_cpu_ns() - since);
      if (since > 0 && busy_from > ready) ready = busy_from;
    }
    if (ready > ts) ready = ts;
    per_frame = ready > 0 ? 2 : 1;
    if (atomic_exchange_explicit(&p->pad_state->last_thread, thread, memory_order_relaxed) == thread) thread = 0;
  } else if (p->point == P_ORIGIN && p->clock == CLOCK_REALTIME) {
    capture = ntp_capture_ns(buf);
    per_frame = capture > 0 ? 2 : 1;
  }
  uint64_t total = (uint64_t)n * per_frame + (thread ? 1 : 0), pos;
  if (!ring_reserve(ring, total, &pos)) {
    atomic_fetch_add_explicit(&ring->dropped, total, memory_order_relaxed);
    return;
  }
  int8_t group = (int8_t)MIN(n, MAX_GROUP);
  for (guint i = 0; i < n; i++) {
    int64_t source = -1, frame = -1;
    /* A malformed entry still publishes its slot (already reserved), marked -1. */
    dcu_value_i64(dcu_field_item(sources, i), &source);
    dcu_value_i64(dcu_field_item(frames, i), &frame);
    DcuEvent ev = {ts, frame, (int32_t)source, p->stage, p->point, 0};
    ring_publish(ring, pos++, &ev);
    if (p->point == P_ENTER && p->enters && source >= 0 && frame >= 0)
      remember_enter(p->enters, frame_key(source, frame), ts, this_thread());
    if (ready > 0) {
      /* The buffer's first frame carries its size, the others minus it: its work counted once. */
      DcuEvent r = {ready, frame, (int32_t)source, p->stage, P_READY, (int8_t)(i == 0 ? group : -group)};
      ring_publish(ring, pos++, &r);
    } else if (capture > 0) {
      DcuEvent c = {capture, frame, (int32_t)source, p->stage, P_CAPTURE, 0};
      ring_publish(ring, pos++, &c);
    }
  }
  if (thread) {
    DcuEvent f = {ts, thread, 0, p->stage, P_FACT, FACT_THREAD};
    ring_publish(ring, pos, &f);
  }
}

/* --- when does a traced src pad's push return? ------------------------------------------- */

static _Atomic uint64_t hook_calls;

void dcu_note_push_returned(GstPad *pad) {
  atomic_fetch_add_explicit(&hook_calls, 1, memory_order_relaxed);
  DcuPadState *st = g_object_get_qdata(G_OBJECT(pad), pad_state_quark);
  if (!st) return;
  atomic_store_explicit(&st->last_post, dcu_clock_ns(st->clock), memory_order_relaxed);
  /* The thread's CPU time is a system call: read only where frames change threads. */
  if (atomic_load_explicit(&st->wants_cpu, memory_order_relaxed))
    atomic_store_explicit(&st->cpu_at_post, thread_cpu_ns(), memory_order_relaxed);
  atomic_store_explicit(&st->post_thread, this_thread(), memory_order_relaxed);
}

/* How many push-post hooks ran (all pads of the process): for benchmarks. */
uint64_t dcu_hook_calls(void) { return atomic_load(&hook_calls); }

static GMutex attach_lock;

static DcuStageEnters *stage_enters(DcuRing *ring, int stage) {
  if (stage < 0 || stage >= MAX_STAGES) return NULL;
  g_mutex_lock(&attach_lock);
  DcuStageEnters *t = atomic_load(&ring->enters[stage]);
  if (!t) {
    t = calloc(1, sizeof(DcuStageEnters));
    atomic_store(&ring->enters[stage], t);
  }
  g_mutex_unlock(&attach_lock);
  return t;
}

static DcuPadState *pad_state(GstPad *pad, clockid_t clock) {
  g_mutex_lock(&attach_lock);
  DcuPadState *st = g_object_get_qdata(G_OBJECT(pad), pad_state_quark);
  if (!st) {
    st = g_new0(DcuPadState, 1);
    st->clock = clock;
    g_object_set_qdata_full(G_OBJECT(pad), pad_state_quark, st, g_free);
  }
  g_mutex_unlock(&attach_lock);
  return st;
}

void dcu_probe_setup(DcuProbe *p, DcuRing *ring, GstPad *pad, int stage, int point, clockid_t clock) {
  init_once();
  memset(p, 0, sizeof(*p));
  p->ring = ring;
  p->clock = clock;
  p->stage = (int16_t)stage;
  p->point = (int8_t)point;
  if (point == P_ENTER || point == P_EXIT) p->enters = stage_enters(ring, stage);
  if (point == P_EXIT && GST_PAD_IS_SRC(pad)) p->pad_state = pad_state(pad, clock);
  atomic_fetch_add(&ring->refcount, 1);
}

void dcu_probe_clear(DcuProbe *p) {
  if (p->ring) ring_unref(p->ring);
  p->ring = NULL;
}

gboolean dcu_pad_splits_lists(GstPad *pad) {
  init_once();
  return GST_PAD_IS_SINK(pad) && GST_PAD_CHAINLISTFUNC(pad) == default_chain_list;
}

/* Append events made elsewhere (drops and facts the node learns from the bus or from its
 * sources) to the ring, as a producer like any probe. Returns how many went in (0 or n). */
uint64_t dcu_push(DcuRing *ring, const void *events, uint64_t n) {
  uint64_t pos;
  if (n == 0) return 0;
  if (!ring_reserve(ring, n, &pos)) {
    atomic_fetch_add_explicit(&ring->dropped, n, memory_order_relaxed);
    return 0;
  }
  const DcuEvent *src = events;
  for (uint64_t i = 0; i < n; i++) ring_publish(ring, pos + i, &src[i]);
  return n;
}

int64_t dcu_clock_ns(clockid_t clock) {
  struct timespec t;
  clock_gettime(clock, &t);
  return (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
}

/* The clock the probes read, for callers that want to compare (tests, headers). */
int64_t dcu_now(int clock_id) { return dcu_clock_ns((clockid_t)clock_id); }
