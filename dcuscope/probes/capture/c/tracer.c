/* The dcuscope GStreamer tracer: per-frame tracepoints in any application, from hooks alone.
 *
 *   GST_PLUGIN_PATH="$(dcuscope plugin-path)" \
 *   GST_TRACERS="dcuscope(node=DCU-1,trace=dcu1.trace.jsonl)" gst-launch-1.0 videotestsrc ! ...
 *
 * Parameters (GStreamer's tracer convention: a structure's fields in the brackets): node (the
 * trace's node name, default the host name), trace (the trace file, default NODE.trace.jsonl),
 * clock (realtime, monotonic or tai; default realtime), capacity (ring size in events). An
 * unknown parameter is a one-line warning.
 *
 * Stages are the elements (not bins) that frames with an identity pass. Tracepoints, from the
 * hooks alone: enter at pad-chain-pre on a stage's sink pad, exit at pad-push-pre on its src
 * pad, ready (service/wait) from pad-push-post (ring.c), the list variants of each.
 *
 * Frame identity: the same frames meta as dcuscope's own framestamp element (a
 * GstReferenceTimestampMeta "timestamp/x-dcuscope-frames" with source and frame fields); where
 * a buffer already carries one (dcuscope's own pipelines) it is used as it is. Otherwise a
 * frame gets one (an origin point) where video starts: a source element producing video, the
 * first element producing video from something else (a demuxer, an RTP depayloader), or the
 * first producing raw video from frames without identity; source ids in the order their first
 * frame appears, frame numbers counted per source from 0. A buffer that is shared where it
 * should get its identity (not writable: some decoders keep a reference) cannot carry it: the
 * tracer counts those frames and says so at exit. Metas follow the frame
 * through 1:1 elements, queues and tee (the same buffer), converters, encoders and decoders
 * (GstBaseTransform, GstVideoEncoder and GstVideoDecoder copy metas without tags). An
 * aggregator (any GstAggregator: compositor, audiomixer...) makes new buffers: each output
 * buffer is given the frames it was made from, per sink pad the frame whose running time
 * covers the output's start (that pad's last frame starting at or before it). An element that
 * takes identified frames in and pushes only buffers without identity (not an aggregator) makes
 * lineage unknowable: it is named in the trace header (lineage_unknown), never guessed.
 *
 * Across pipelines (links.h): a frame a sink sends to another pipeline (RTP packets: udpsink; a
 * shmsink's buffer) gets a link event when the push into the sink returns, and a frame that came
 * from one (the first frame of its RTP packets a depayloader makes, or a decoder after it; a
 * shmsrc's buffer) one when its first packet left the pipeline's source element (udpsrc), each
 * with its key: model/journeys.py joins the two ends.
 */

#include "tracer.h"

#include "deepstream.h"
#include "graph.h"
#include "links.h"
#include "writer.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define DEFAULT_CAPACITY (1 << 18)
#define AGG_HISTORY 16
#define AGG_MAX_FRAMES 64
#define FROM_UNKNOWN INT64_MIN

typedef struct {
  int64_t start; /* running time of the buffer's first nanosecond, FROM_UNKNOWN if none */
  guint n;
  int64_t source[AGG_MAX_FRAMES];
  int64_t frame[AGG_MAX_FRAMES];
  int64_t origin[AGG_MAX_FRAMES];
} DcuAggEntry;

/* The recent identified buffers of one aggregator sink pad (written on the pad's streaming
 * thread, read on the aggregator's). */
typedef struct {
  GMutex lock;
  guint written;
  DcuAggEntry entries[AGG_HISTORY];
} DcuAggHistory;

typedef struct {
  DcuProbe probe;   /* enter (sink pad) or exit (src pad) */
  DcuProbe origin;  /* src pads: the origin point, where frames get their identity */
  DcuStage *stage;  /* NULL: not traced (a bin's ghost pad, a proxy pad) */
  int stamps;       /* src pads: -1 undecided, 0 never gives frames an identity, 1 does */
  int source;       /* the source id it gives, -1 before its first frame */
  _Atomic int64_t next_frame;
  DcuAggHistory *history; /* sink pads of an aggregator */
  _Atomic int active;     /* in-process tracepoints: 0 once detached (freed with the pad) */
  int link_out;           /* sink pads of a sink: -1 undecided, 0 none, else the LINK_*_OUT it sends */
  int source_out;         /* src pads of source elements: -1 undecided, 0 none, SOURCE_RTP (udpsrc), SOURCE_SHM */
  int64_t last_key;       /* the key of the last RTP packet it sent or pushed */
  DcuPackets *packets;    /* sink pads taking RTP packets in (a depayloader's); a shmsrc's src pad */
  int rtp_in;             /* -1 undecided, 0 no, 1 packets kept */
} DcuPadInfo;

#define MAX_LINKED 16
enum { SOURCE_RTP = 1, SOURCE_SHM = 2 };

/* A frame handed to a link-out sink (udpsink, shmsink) on this thread: recorded when the push into
 * it returns (the packet or the buffer is sent then), by the push-post hook on the same thread. */
typedef struct {
  GstPad *pad; /* the sink pad it entered; NULL: none pending */
  DcuRing *ring;
  clockid_t clock;
  int stage, kind, n;
  int64_t key;
  int64_t source[MAX_LINKED], frame[MAX_LINKED];
} PendingLink;

static _Thread_local PendingLink pending_link;

typedef struct {
  GstTracer parent;
  DcuRing *ring;
  clockid_t clock;
  DcuGraph graph;
  DcuWriter *writer;
  GQuark pad_quark, stage_quark;
  GType aggregator_type;
  gboolean in_process; /* made by dcu_hook_attach: traces only the pads placed on it */
  _Atomic int finished; /* dcu_tracer_finish: its trace is closed, its hooks do nothing */
  gboolean deepstream;  /* read frames from DeepStream's NvDsBatchMeta (deepstream=1; untested) */
  gboolean pre_hooks;  /* its push/chain-pre hooks are registered */
  gboolean chain_hooks; /* GStreamer has pad-chain hooks (1.22 and later): see enter_peer */
  DcuArrivals *arrivals; /* RTP frames' first packets from source elements: links in (kept while pads may use it) */
  _Atomic int link_ends; /* a pad took RTP packets in or a source element pushed RTP or shm: frames may have
                            come from another pipeline (until then, origins look for none) */
} GstDcuscopeTracer;

typedef struct {
  GstTracerClass parent_class;
} GstDcuscopeTracerClass;

G_DEFINE_TYPE(GstDcuscopeTracer, gst_dcuscope_tracer, GST_TYPE_TRACER)

/* The GST_TRACERS one, whose trace an exit handler finishes: applications that never call
 * gst_deinit() still get a complete trace. */
static GstDcuscopeTracer *live_tracer;

static const char *const CLOCK_NAMES[] = {"realtime", "monotonic", "tai"};
static const clockid_t CLOCK_IDS[] = {CLOCK_REALTIME, CLOCK_MONOTONIC, CLOCK_TAI};
static const char *const KNOWN_PARAMS[] = {"node", "trace", "clock", "capacity", "deepstream", NULL};

/* --- stages and pads ------------------------------------------------------------------------ */

static gboolean name_taken(DcuGraph *g, const char *name) {
  for (int i = 0; i < g->n_stages; i++)
    if (g->stages[i] && strcmp(g->stages[i]->name, name) == 0) return TRUE;
  return FALSE;
}

/* The element's stage, made on first sight (graph lock held). NULL when there are too many. */
static DcuStage *stage_of(GstDcuscopeTracer *self, GstElement *element) {
  DcuStage *st = g_object_get_qdata(G_OBJECT(element), self->stage_quark);
  if (st) return st;
  DcuGraph *g = &self->graph;
  if (g->n_stages >= MAX_STAGES) return NULL;
  st = g_new0(DcuStage, 1);
  st->index = g->n_stages;
  g_weak_ref_init(&st->element, element);
  GstElementFactory *factory = gst_element_get_factory(element);
  st->factory = g_strdup(factory ? GST_OBJECT_NAME(factory) : G_OBJECT_TYPE_NAME(element));
  const char *base = GST_OBJECT_NAME(element);
  st->name = g_strdup(base);
  for (int k = 1; name_taken(g, st->name); k++) {
    g_free(st->name);
    st->name = g_strdup_printf("%s_%d", base, k);
  }
  if (!self->aggregator_type) self->aggregator_type = g_type_from_name("GstAggregator"); /* once loaded */
  st->aggregator = self->aggregator_type && g_type_is_a(G_OBJECT_TYPE(element), self->aggregator_type);
  st->source_element = element->numsinkpads == 0;
  /* Sinks drop late buffers (QoS): remember their inputs from the start, to name those frames. */
  if (GST_OBJECT_FLAG_IS_SET(element, GST_ELEMENT_FLAG_SINK)) atomic_store(&st->keep_history, 1);
  /* Stages live as long as the tracer (the graph lists them); the element only points at it. */
  g->stages[g->n_stages++] = st;
  g_object_set_qdata(G_OBJECT(element), self->stage_quark, st);
  return st;
}

static void pad_info_free(gpointer data) {
  DcuPadInfo *info = data;
  dcu_probe_clear(&info->probe);
  dcu_probe_clear(&info->origin);
  if (info->history) {
    g_mutex_clear(&info->history->lock);
    g_free(info->history);
  }
  if (info->packets) {
    g_mutex_clear(&info->packets->lock);
    g_free(info->packets);
  }
  g_free(info);
}

static DcuPadInfo *make_pad_info(GstDcuscopeTracer *self, GstPad *pad) {
  DcuPadInfo *info = g_new0(DcuPadInfo, 1);
  info->stamps = -1;
  info->source = -1;
  info->link_out = info->source_out = info->rtp_in = -1;
  info->last_key = -1;
  GstObject *parent = GST_OBJECT_PARENT(pad);
  if (!parent || !GST_IS_ELEMENT(parent) || GST_IS_BIN(parent)) return info; /* ghost or proxy pad */
  DcuStage *st = stage_of(self, GST_ELEMENT(parent));
  if (!st) return info;
  info->stage = st;
  gboolean sink = GST_PAD_IS_SINK(pad);
  dcu_probe_setup(&info->probe, self->ring, pad, st->index, sink ? P_ENTER : P_EXIT, self->clock);
  if (!sink) {
    dcu_probe_setup(&info->origin, self->ring, pad, st->index, P_ORIGIN, self->clock);
    /* A pad that pushes is linked: note the link now, while both elements surely exist. */
    GstElement *next = dcu_downstream_element(pad);
    DcuStage *to = next ? stage_of(self, next) : NULL;
    if (to) self->graph.edges[st->index * MAX_STAGES + to->index] = 1;
    if (next) gst_object_unref(next);
  }
  if (sink && st->aggregator) {
    info->history = g_new0(DcuAggHistory, 1);
    g_mutex_init(&info->history->lock);
  }
  return info;
}

/* The pad's tracing state; made on the pad's first buffer (the element is named by then). */
static inline DcuPadInfo *pad_info(GstDcuscopeTracer *self, GstPad *pad) {
  DcuPadInfo *info = g_object_get_qdata(G_OBJECT(pad), self->pad_quark);
  if (G_LIKELY(info)) return info;
  g_mutex_lock(&self->graph.lock);
  info = g_object_get_qdata(G_OBJECT(pad), self->pad_quark);
  if (!info) {
    info = make_pad_info(self, pad);
    g_object_set_qdata_full(G_OBJECT(pad), self->pad_quark, info, pad_info_free);
  }
  g_mutex_unlock(&self->graph.lock);
  return info;
}

/* --- frame identity ------------------------------------------------------------------------- */

static gboolean caps_named(GstCaps *caps, const char *prefix, gboolean whole) {
  if (!caps || gst_caps_get_size(caps) == 0) return FALSE;
  const char *name = gst_structure_get_name(gst_caps_get_structure(caps, 0));
  return whole ? strcmp(name, prefix) == 0 : g_str_has_prefix(name, prefix);
}

/* Containers are video/... too (video/x-matroska, video/quicktime, video/mpegts): bytes, not frames. */
static const char *const CONTAINERS[] = {"video/x-matroska", "video/quicktime", "video/mpegts", "video/x-msvideo",
                                         "video/webm", "video/x-flv", "video/mj2", "video/x-ms-asf", NULL};

static gboolean video_frames(GstCaps *caps) {
  if (!caps_named(caps, "video/", FALSE)) return FALSE;
  const GstStructure *s = gst_caps_get_structure(caps, 0);
  const char *name = gst_structure_get_name(s);
  for (int i = 0; CONTAINERS[i]; i++)
    if (strcmp(name, CONTAINERS[i]) == 0) return FALSE;
  gboolean system = FALSE;
  return !(gst_structure_get_boolean(s, "systemstream", &system) && system);
}

static gboolean any_sink_caps(GstPad *pad, const char *prefix, gboolean whole) {
  gboolean found = FALSE;
  GstObject *parent = gst_pad_get_parent(pad);
  if (!parent) return FALSE;
  GstElement *element = GST_ELEMENT(parent);
  GST_OBJECT_LOCK(element);
  for (GList *l = element->sinkpads; l; l = l->next) {
    GstCaps *in = gst_pad_get_current_caps(GST_PAD(l->data));
    if (in && (whole ? caps_named(in, prefix, TRUE) : video_frames(in))) found = TRUE;
    if (in) gst_caps_unref(in);
  }
  GST_OBJECT_UNLOCK(element);
  gst_object_unref(parent);
  return found;
}

/* Does this src pad give frames their identity? Where video starts: a source element's video,
 * the first element producing video from something else (a demuxer, an RTP depayloader: the
 * encoded frames, whose metas decoders carry on to the pictures), or the first producing raw
 * video from frames that came without identity. -1 while the pad has no caps. */
static int decide_stamps(GstPad *pad, DcuStage *st) {
  GstCaps *caps = gst_pad_get_current_caps(pad);
  if (!caps) return -1;
  int stamps = 0;
  if (video_frames(caps)) {
    if (st->source_element || !any_sink_caps(pad, "video/", FALSE)) stamps = 1;
    else if (caps_named(caps, "video/x-raw", TRUE) && !atomic_load(&st->entered) &&
             !any_sink_caps(pad, "video/x-raw", TRUE))
      stamps = 1;
  }
  gst_caps_unref(caps);
  return stamps;
}

static const char *const DESCRIBING[] = {"uri", "location", "device", NULL};

static char *describe_source(GstElement *element) {
  for (int i = 0; DESCRIBING[i]; i++) {
    GParamSpec *spec = g_object_class_find_property(G_OBJECT_GET_CLASS(element), DESCRIBING[i]);
    if (spec && spec->value_type == G_TYPE_STRING && (spec->flags & G_PARAM_READABLE)) {
      char *value = NULL;
      g_object_get(element, DESCRIBING[i], &value, NULL);
      if (value && *value) return value;
      g_free(value);
    }
  }
  return g_strdup(GST_OBJECT_NAME(element));
}

/* The pad's source id, given on its first frame (one per pad even if two threads race). */
static int source_of(GstDcuscopeTracer *self, DcuPadInfo *info, GstPad *pad) {
  if (G_LIKELY(info->source >= 0)) return info->source;
  DcuGraph *g = &self->graph;
  GstObject *parent = gst_pad_get_parent(pad);
  char *description = parent ? describe_source(GST_ELEMENT(parent)) : g_strdup("?");
  if (parent) gst_object_unref(parent);
  g_mutex_lock(&g->lock);
  if (info->source < 0 && g->n_sources < MAX_SOURCES) {
    info->source = g->n_sources++;
    g->sources[info->source] = description;
    description = NULL;
    atomic_fetch_add(&g->version, 1);
  }
  g_mutex_unlock(&g->lock);
  g_free(description);
  return info->source;
}

static void add_frames_meta(GstBuffer *buf, GstStructure *s, int64_t ts) {
  GstCaps *caps = gst_caps_new_full(s, NULL);
  gst_buffer_add_reference_timestamp_meta(buf, caps, (GstClockTime)ts, GST_CLOCK_TIME_NONE);
  gst_caps_unref(caps);
}

/* Give buf the identity of the next frame of the pad's source; FALSE when buf is shared (its
 * metadata cannot be written). */
static gboolean stamp(GstDcuscopeTracer *self, DcuPadInfo *info, GstPad *pad, GstBuffer *buf, int64_t ts,
                      int64_t *frame) {
  if (!gst_buffer_is_writable(buf) || source_of(self, info, pad) < 0) return FALSE;
  *frame = atomic_fetch_add_explicit(&info->next_frame, 1, memory_order_relaxed);
  int64_t source = info->source;
  add_frames_meta(buf, dcu_frames_new(1, &source, frame, &ts), ts);
  return TRUE;
}

static int64_t running_time(GstPad *pad, GstClockTime pts) {
  if (!GST_CLOCK_TIME_IS_VALID(pts)) return FROM_UNKNOWN;
  GstEvent *event = gst_pad_get_sticky_event(pad, GST_EVENT_SEGMENT, 0);
  if (!event) return FROM_UNKNOWN;
  const GstSegment *segment;
  gst_event_parse_segment(event, &segment);
  int64_t rt = FROM_UNKNOWN;
  if (segment->format == GST_FORMAT_TIME) {
    guint64 t = gst_segment_to_running_time(segment, GST_FORMAT_TIME, pts);
    if (GST_CLOCK_TIME_IS_VALID(t)) rt = (int64_t)t;
  }
  gst_event_unref(event);
  return rt;
}

/* An identified buffer entered an aggregator's sink pad: remember its frames and running time. */
static void remember_input(DcuPadInfo *info, GstPad *pad, GstBuffer *buf, const GstStructure *s) {
  DcuAggHistory *h = info->history;
  int64_t start = running_time(pad, GST_BUFFER_PTS(buf));
  g_mutex_lock(&h->lock);
  DcuAggEntry *e = &h->entries[h->written++ % AGG_HISTORY];
  e->start = start;
  e->n = MIN(dcu_frames_count(s), AGG_MAX_FRAMES);
  for (guint i = 0; i < e->n; i++) {
    dcu_frames_get(s, i, &e->source[i], &e->frame[i]);
    e->origin[i] = dcu_frames_origin(s, i);
  }
  g_mutex_unlock(&h->lock);
}

/* Give an aggregator's output buffer the frames it was made from: per sink pad, the last
 * remembered frame that starts at or before the output's running time. FALSE if none. */
static gboolean aggregate_lineage(GstElement *element, GstPad *src, GstBuffer *buf, GQuark pad_quark, int64_t ts) {
  if (!gst_buffer_is_writable(buf)) return FALSE;
  int64_t out = running_time(src, GST_BUFFER_PTS(buf));
  GArray *sources = g_array_new(FALSE, FALSE, sizeof(int64_t)), *frames = g_array_new(FALSE, FALSE, sizeof(int64_t)),
         *origins = g_array_new(FALSE, FALSE, sizeof(int64_t));
  GST_OBJECT_LOCK(element);
  for (GList *l = element->sinkpads; l; l = l->next) {
    DcuPadInfo *info = g_object_get_qdata(G_OBJECT(l->data), pad_quark);
    if (!info || !info->history) continue;
    DcuAggHistory *h = info->history;
    g_mutex_lock(&h->lock);
    const DcuAggEntry *best = NULL;
    guint first = h->written > AGG_HISTORY ? h->written - AGG_HISTORY : 0;
    for (guint k = first; k < h->written; k++) {
      const DcuAggEntry *e = &h->entries[k % AGG_HISTORY];
      if (out == FROM_UNKNOWN || e->start == FROM_UNKNOWN) best = e; /* no times: the latest */
      else if (e->start <= out && (!best || e->start >= best->start)) best = e;
    }
    if (best) {
      g_array_append_vals(sources, best->source, best->n);
      g_array_append_vals(frames, best->frame, best->n);
      g_array_append_vals(origins, best->origin, best->n);
    }
    g_mutex_unlock(&h->lock);
  }
  GST_OBJECT_UNLOCK(element);
  guint total = sources->len;
  if (total > 0)
    add_frames_meta(buf, dcu_frames_new(total, (int64_t *)sources->data, (int64_t *)frames->data,
                                        (int64_t *)origins->data), ts);
  g_array_free(sources, TRUE);
  g_array_free(frames, TRUE);
  g_array_free(origins, TRUE);
  return total > 0;
}

/* --- links between pipelines (links.h) ------------------------------------------------------ */

static const char *factory_name(GstElement *element) {
  GstElementFactory *factory = element ? gst_element_get_factory(element) : NULL;
  return factory ? GST_OBJECT_NAME(factory) : "";
}

static gboolean pad_caps_named(GstPad *pad, const char *name) {
  GstCaps *caps = gst_pad_get_current_caps(pad);
  gboolean named = caps_named(caps, name, TRUE);
  if (caps) gst_caps_unref(caps);
  return named;
}

/* What a sink's sink pad sends on to another pipeline: RTP packets (udpsink and its kind, any
 * sink taking application/x-rtp) or shared memory (shmsink); 0 for any other pad. */
static int decide_link_out(GstPad *pad) {
  GstElement *element = GST_ELEMENT(GST_OBJECT_PARENT(pad));
  if (element->numsrcpads > 0) return 0;
  if (pad_caps_named(pad, "application/x-rtp")) return LINK_RTP_OUT;
  return strcmp(factory_name(element), "shmsink") == 0 ? LINK_SHM_OUT : 0;
}

/* An identified buffer entered a sink pad: if it sends the buffer's frames to another pipeline,
 * remember them (a new RTP frame: its first packet) until the push into it returns. */
static void link_out_enter(DcuPadInfo *info, GstPad *pad, GstBuffer *buf, const GstStructure *s) {
  if (G_LIKELY(info->link_out == 0)) return;
  if (info->link_out < 0) info->link_out = decide_link_out(pad);
  if (info->link_out == 0) return;
  int64_t key = info->link_out == LINK_RTP_OUT ? dcu_rtp_key(buf) : dcu_bytes_key(buf);
  if (key < 0 || (info->link_out == LINK_RTP_OUT && key == info->last_key)) return;
  info->last_key = key;
  PendingLink *p = &pending_link;
  p->pad = pad;
  p->ring = info->probe.ring;
  p->clock = info->probe.clock;
  p->stage = info->probe.stage;
  p->kind = info->link_out;
  p->key = key;
  p->n = (int)MIN(dcu_frames_count(s), MAX_LINKED);
  for (int i = 0; i < p->n; i++) dcu_frames_get(s, (guint)i, &p->source[i], &p->frame[i]);
}

/* A push returned: if it was the one into the link-out sink this thread last entered, its frames
 * are sent now. */
static void link_out_sent(GstPad *pad) {
  PendingLink *p = &pending_link;
  if (G_LIKELY(p->pad == NULL) || GST_PAD_PEER(pad) != p->pad) return;
  int64_t ts = dcu_clock_ns(p->clock);
  for (int i = 0; i < p->n; i++) dcu_link_record(p->ring, p->stage, p->kind, ts, p->key, p->source[i], p->frame[i]);
  p->pad = NULL;
}

static DcuPackets *packets_new(void) {
  DcuPackets *packets = g_new0(DcuPackets, 1);
  g_mutex_init(&packets->lock);
  return packets;
}

/* A source element's src pad pushed a buffer without identity: where it pushes RTP packets
 * (udpsrc), note when each frame's first packet came; where it is a shmsrc, the key of each
 * buffer's bytes by PTS (converters after it change the bytes, not the PTS). */
static void source_out(GstDcuscopeTracer *self, DcuPadInfo *info, GstPad *pad, GstBuffer *buf, int64_t ts) {
  if (info->source_out < 0) {
    GstElement *element = GST_ELEMENT(GST_OBJECT_PARENT(pad));
    info->source_out = element->numsinkpads > 0 ? 0
                       : pad_caps_named(pad, "application/x-rtp") ? SOURCE_RTP
                       : strcmp(factory_name(element), "shmsrc") == 0 ? SOURCE_SHM : 0;
    if (info->source_out == SOURCE_SHM) g_atomic_pointer_set(&info->packets, packets_new());
    if (info->source_out) atomic_store(&self->link_ends, 1);
  }
  if (info->source_out == SOURCE_SHM) {
    int64_t key = GST_CLOCK_TIME_IS_VALID(GST_BUFFER_PTS(buf)) ? dcu_bytes_key(buf) : -1;
    if (key >= 0) dcu_packets_note(info->packets, GST_BUFFER_PTS(buf), key, ts);
    return;
  }
  if (info->source_out != SOURCE_RTP) return;
  int64_t key = dcu_rtp_key(buf);
  if (key < 0 || key == info->last_key) return;
  info->last_key = key;
  dcu_arrivals_note(self->arrivals, key, ts);
}

/* A buffer without identity entered a sink pad: a depayloader's (RTP in, video out) keeps its packets. */
static void rtp_packet_in(GstDcuscopeTracer *self, DcuPadInfo *info, GstPad *pad, GstBuffer *buf, int64_t ts) {
  if (G_LIKELY(info->rtp_in == 0)) return;
  if (info->rtp_in < 0) {
    GstElement *element = GST_ELEMENT(GST_OBJECT_PARENT(pad));
    info->rtp_in = element->numsrcpads > 0 && pad_caps_named(pad, "application/x-rtp");
    if (info->rtp_in) {
      g_atomic_pointer_set(&info->packets, packets_new());
      atomic_store(&self->link_ends, 1);
    }
  }
  int64_t key = info->rtp_in ? dcu_rtp_key(buf) : -1;
  if (key >= 0) dcu_packets_note(info->packets, GST_BUFFER_PTS(buf), key, ts);
}

/* The key and time of the buffer of PTS pts that one of element's pads (its sink pads, or, a
 * source element, its src pads) passed, as remembered there; FALSE if none is. */
static gboolean passed_here(GstDcuscopeTracer *self, GstElement *element, GstClockTime pts, int64_t *key,
                            int64_t *first) {
  gboolean found = FALSE;
  GST_OBJECT_LOCK(element);
  for (GList *l = element->numsinkpads ? element->sinkpads : element->srcpads; l && !found; l = l->next) {
    DcuPadInfo *in = g_object_get_qdata(G_OBJECT(l->data), self->pad_quark);
    DcuPackets *packets = in ? g_atomic_pointer_get(&in->packets) : NULL;
    found = packets && dcu_packets_find(packets, pts, key, first);
  }
  GST_OBJECT_UNLOCK(element);
  return found;
}

/* Where the frame element gives an identity to came from: walking up from element through elements
 * of one sink pad (a decoder, a converter, a bin such as decodebin; at most 12), the first that
 * remembers the buffer of the frame's PTS: a depayloader's RTP packets (their key, when the first
 * came), a shmsrc's buffer (the key of its bytes). A shmsrc that remembers none (no PTS) gives the
 * key of buf's bytes, which elements between it and element left as they were (a capsfilter).
 * The kind of link, or 0 when the frame came from neither. */
static int upstream_link(GstDcuscopeTracer *self, GstElement *element, GstBuffer *buf, int64_t *key, int64_t *first) {
  int kind = 0;
  gst_object_ref(element);
  for (int hops = 0; hops < 12 && element && kind == 0; hops++) {
    gboolean source = element->numsinkpads == 0;
    gboolean shm = source && strcmp(factory_name(element), "shmsrc") == 0;
    if (passed_here(self, element, GST_BUFFER_PTS(buf), key, first)) kind = shm ? LINK_SHM_IN : LINK_RTP_IN;
    else if (shm && (*key = dcu_bytes_key(buf)) >= 0) kind = LINK_SHM_IN;
    if (source || kind) break;
    GstElement *up = NULL;
    GST_OBJECT_LOCK(element);
    GstPad *sink = element->numsinkpads == 1 ? gst_object_ref(GST_PAD(element->sinkpads->data)) : NULL;
    GST_OBJECT_UNLOCK(element);
    if (sink) {
      GstPad *peer = gst_pad_get_peer(sink);
      if (peer) {
        up = gst_pad_get_parent_element(peer);
        gst_object_unref(peer);
      }
      gst_object_unref(sink);
    }
    gst_object_unref(element);
    element = up;
  }
  if (element) gst_object_unref(element);
  return kind;
}

/* Frame (source, frame) got its identity on pad: if it came from another pipeline, record where
 * it entered this one (RTP: when its first packet left the pipeline's source element, else
 * entered its depayloader; shm: when shmsrc pushed it, else now) at stage, into ring. */
static void link_in(GstDcuscopeTracer *self, DcuRing *ring, int stage, GstPad *pad, GstBuffer *buf, int64_t ts,
                    int64_t source, int64_t frame) {
  if (G_LIKELY(!atomic_load_explicit(&self->link_ends, memory_order_relaxed))) return;
  int64_t key = -1, first = ts;
  int kind = upstream_link(self, GST_ELEMENT(GST_OBJECT_PARENT(pad)), buf, &key, &first);
  if (kind == 0) return;
  int64_t arrived = first;
  if (kind == LINK_RTP_IN && dcu_arrivals_find(self->arrivals, key, &arrived) && arrived > first) arrived = first;
  dcu_link_record(ring, stage, kind, arrived, key, source, frame);
}

/* An origin tracepoint placed in process (a framestamp's src pad) recorded buf: its frames may
 * have come from another pipeline. */
static void origin_link_in(GstDcuscopeTracer *self, DcuPadInfo *info, GstPad *pad, GstBuffer *buf, int64_t ts) {
  if (G_LIKELY(!atomic_load_explicit(&self->link_ends, memory_order_relaxed))) return;
  const GstStructure *s = dcu_frames_structure(buf);
  if (!s || dcu_frames_count(s) != 1) return;
  int64_t source, frame;
  dcu_frames_get(s, 0, &source, &frame);
  link_in(self, info->probe.ring, info->probe.stage, pad, buf, ts, source, frame);
}

/* --- hooks ---------------------------------------------------------------------------------- */

/* DeepStream (deepstream=1): a batch that carries NvDsBatchMeta and not our meta. Frames start
 * where batches first appear (nvstreammux: an origin); the buffer gets our meta when it can,
 * so that the stages after read that. */
static gboolean deepstream_exit(DcuPadInfo *info, DcuStage *st, GstBuffer *buf, int64_t ts) {
  GstStructure *ds = dcu_deepstream_frames(buf, ts);
  if (!ds) return FALSE;
  gboolean origin = !atomic_load_explicit(&st->entered, memory_order_relaxed);
  if (gst_buffer_is_writable(buf)) add_frames_meta(buf, gst_structure_copy(ds), ts);
  dcu_record_frames(origin ? &info->origin : &info->probe, ds, buf, ts);
  gst_structure_free(ds);
  return TRUE;
}

/* The time of a hook call, read once per call (a list shares it) and only for traced pads. */
static inline int64_t now_for(DcuPadInfo *info, int64_t *ts) {
  if (*ts == 0) *ts = dcu_clock_ns(info->probe.clock);
  return *ts;
}

/* The pad's state if this hook call records anything on it: in process, the tracepoint placed
 * on it (still active); else its stage's pad, made on first sight. NULL: nothing to record. */
static inline DcuPadInfo *traced_pad(GstDcuscopeTracer *self, GstPad *pad) {
  if (self->in_process) {
    DcuPadInfo *info = g_object_get_qdata(G_OBJECT(pad), self->pad_quark);
    return info && atomic_load_explicit(&info->active, memory_order_relaxed) ? info : NULL;
  }
  if (G_UNLIKELY(atomic_load_explicit(&self->finished, memory_order_relaxed))) return NULL;
  DcuPadInfo *info = pad_info(self, pad);
  return info->stage ? info : NULL;
}

static void frame_exit(GstDcuscopeTracer *self, GstPad *pad, GstBuffer *buf, int64_t *when) {
  DcuPadInfo *info = traced_pad(self, pad);
  if (!info) return;
  int64_t ts = now_for(info, when);
  if (self->in_process) {
    if (info->probe.point == P_LINK) {  /* a watch: a source element's pad (udpsrc, shmsrc) */
      if (!dcu_frames_structure(buf)) source_out(self, info, pad, buf, ts);
      return;
    }
    dcu_record_buffer(&info->probe, buf, ts);
    if (info->probe.point == P_ORIGIN) origin_link_in(self, info, pad, buf, ts);
    return;
  }
  DcuStage *st = info->stage;
  if (G_LIKELY(dcu_frames_structure(buf) != NULL)) {
    if (G_UNLIKELY(!atomic_load_explicit(&st->pushed_identified, memory_order_relaxed)))
      atomic_store(&st->pushed_identified, 1);
    dcu_record_buffer(&info->probe, buf, ts);
    return;
  }
  if (self->deepstream && deepstream_exit(info, st, buf, ts)) return;
  if (G_UNLIKELY(info->source_out != 0)) source_out(self, info, pad, buf, ts);
  if (st->aggregator && atomic_load_explicit(&st->entered, memory_order_relaxed)) {
    GstObject *parent = GST_OBJECT_PARENT(pad);
    if (parent && aggregate_lineage(GST_ELEMENT(parent), pad, buf, self->pad_quark, ts)) {
      dcu_record_buffer(&info->probe, buf, ts);
      return;
    }
  }
  if (info->stamps < 0) info->stamps = self->deepstream ? 0 : decide_stamps(pad, st);
  if (info->stamps == 1) {
    int64_t frame;
    if (stamp(self, info, pad, buf, ts, &frame)) {
      dcu_record_buffer(&info->origin, buf, ts);
      link_in(self, self->ring, st->index, pad, buf, ts, info->source, frame);
      return;
    }
    atomic_fetch_add_explicit(&st->shared, 1, memory_order_relaxed);
  }
  dcu_record_buffer(&info->probe, buf, ts); /* counts it unidentified */
  /* Frames came in, none went out with their identity: lineage stops here (a muxer's headers
   * beside its frames, or a parser's parameter sets, do not count: frames do go out). */
  if (atomic_load_explicit(&st->entered, memory_order_relaxed) &&
      atomic_fetch_add_explicit(&st->unidentified_out, 1, memory_order_relaxed) + 1 == LINEAGE_LOST_AFTER)
    atomic_fetch_add(&self->graph.version, 1);
}

static void frame_enter(GstDcuscopeTracer *self, GstPad *pad, GstBuffer *buf, int64_t *when) {
  DcuPadInfo *info = traced_pad(self, pad);
  if (!info) return;
  int64_t ts = now_for(info, when);
  if (self->in_process) {
    if (info->probe.point == P_LINK) {  /* a watch: a link-out sink's pad, or a depayloader's */
      const GstStructure *s = dcu_frames_structure(buf);
      if (s) link_out_enter(info, pad, buf, s);
      else rtp_packet_in(self, info, pad, buf, ts);
      return;
    }
    dcu_record_buffer(&info->probe, buf, ts);
    return;
  }
  const GstStructure *s = dcu_frames_structure(buf);
  GstStructure *ds = (!s && self->deepstream) ? dcu_deepstream_frames(buf, ts) : NULL;
  if (ds) s = ds;
  if (s) {
    if (G_UNLIKELY(!atomic_load_explicit(&info->stage->entered, memory_order_relaxed)))
      atomic_store(&info->stage->entered, 1);
    if (G_UNLIKELY(!info->history && atomic_load_explicit(&info->stage->keep_history, memory_order_relaxed))) {
      DcuAggHistory *h = g_new0(DcuAggHistory, 1);
      g_mutex_init(&h->lock);
      g_atomic_pointer_set(&info->history, h); /* only this pad's streaming thread writes it */
    }
    if (info->history) remember_input(info, pad, buf, s);
    link_out_enter(info, pad, buf, s);
  } else {
    rtp_packet_in(self, info, pad, buf, ts);
  }
  dcu_record_frames(&info->probe, s, buf, ts);
  if (ds) gst_structure_free(ds);
}

typedef void (*FrameHook)(GstDcuscopeTracer *self, GstPad *pad, GstBuffer *buf, int64_t *when);

/* Each buffer of a list, all at the one time the list crossed the pad (*ts: 0 until read). */
static void each_buffer(GstDcuscopeTracer *self, GstPad *pad, GstBufferList *list, FrameHook hook, int64_t *ts) {
  guint n = gst_buffer_list_length(list);
  for (guint i = 0; i < n; i++) hook(self, pad, gst_buffer_list_get(list, i), ts);
}

/* GStreamer before 1.22 has no pad-chain hooks: a frame enters an element when the pad before
 * pushes it to the element's sink pad, at the same moment, in the same thread. A ghost pad (or
 * its proxy) between them is no stage: its own push to the element's pad is hooked in turn. */
static void enter_peer(GstDcuscopeTracer *self, GstPad *pad, GstBuffer *buf, GstBufferList *list, int64_t *ts) {
  GstPad *peer = gst_pad_get_peer(pad);
  if (!peer) return;
  if (list) each_buffer(self, peer, list, frame_enter, ts);
  else frame_enter(self, peer, buf, ts);
  gst_object_unref(peer);
}

static void on_push_pre(GObject *obj, GstClockTime t, GstPad *pad, GstBuffer *buf) {
  (void)t;
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)obj;
  int64_t ts = 0;
  frame_exit(self, pad, buf, &ts);
  if (!self->chain_hooks) enter_peer(self, pad, buf, NULL, &ts);
}

static void on_push_list_pre(GObject *obj, GstClockTime t, GstPad *pad, GstBufferList *list) {
  (void)t;
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)obj;
  int64_t ts = 0;
  each_buffer(self, pad, list, frame_exit, &ts);
  if (!self->chain_hooks) enter_peer(self, pad, NULL, list, &ts);
}

static void on_chain_pre(GObject *obj, GstClockTime t, GstPad *pad, GstBuffer *buf) {
  (void)t;
  int64_t ts = 0;
  frame_enter((GstDcuscopeTracer *)obj, pad, buf, &ts);
}

static void on_chain_list_pre(GObject *obj, GstClockTime t, GstPad *pad, GstBufferList *list) {
  (void)t;
  /* Split by GStreamer and chained buffer by buffer: those calls record them. */
  int64_t ts = 0;
  if (!dcu_pad_splits_lists(pad)) each_buffer((GstDcuscopeTracer *)obj, pad, list, frame_enter, &ts);
}

/* dcuscope's own mux posts a "dcuscope-drop" element message per frame it drops (late, or
 * still queued when a live run stops): in any application, those are drop events too. */
static const char *const DROP_REASONS[] = {"unknown", "late", "qos", "queue full", "error", "stopped", NULL};

static void element_drop(GstDcuscopeTracer *self, DcuStage *st, const GstStructure *s) {
  int source = -1, code = 0;
  guint64 frame = 0;
  const char *reason = gst_structure_get_string(s, "reason");
  if (!gst_structure_get_int(s, "source", &source) || !gst_structure_get_uint64(s, "frame", &frame) || source < 0)
    return;
  for (int i = 0; reason && DROP_REASONS[i]; i++)
    if (strcmp(reason, DROP_REASONS[i]) == 0) code = i;
  DcuEvent drop = {dcu_clock_ns(self->clock), (int64_t)frame, source, (int16_t)st->index, P_DROP, (int8_t)code};
  dcu_push(self->ring, &drop, 1);
}

static void on_message(GObject *obj, GstClockTime t, GstElement *element, GstMessage *message) {
  (void)t;
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)obj;
  GstMessageType type = GST_MESSAGE_TYPE(message);
  if ((type != GST_MESSAGE_QOS && type != GST_MESSAGE_ELEMENT) || self->in_process ||
      atomic_load_explicit(&self->finished, memory_order_relaxed))
    return;
  DcuStage *st = g_object_get_qdata(G_OBJECT(element), self->stage_quark);
  if (!st) return;
  if (type == GST_MESSAGE_ELEMENT) {
    const GstStructure *s = gst_message_get_structure(message);
    if (s && gst_structure_has_name(s, "dcuscope-drop")) element_drop(self, st, s);
    return;
  }
  atomic_store(&st->keep_history, 1);
  gboolean live;
  guint64 running, stream, timestamp, duration;
  gst_message_parse_qos(message, &live, &running, &stream, &timestamp, &duration);
  DcuEvent drops[AGG_MAX_FRAMES];
  guint n = 0;
  GST_OBJECT_LOCK(element);
  for (GList *l = element->sinkpads; l && n == 0; l = l->next) {
    DcuPadInfo *info = g_object_get_qdata(G_OBJECT(l->data), self->pad_quark);
    DcuAggHistory *h = info ? g_atomic_pointer_get(&info->history) : NULL;
    if (!h) continue;
    g_mutex_lock(&h->lock);
    guint first = h->written > AGG_HISTORY ? h->written - AGG_HISTORY : 0;
    for (guint k = first; k < h->written && n == 0; k++) {
      const DcuAggEntry *e = &h->entries[k % AGG_HISTORY];
      if (GST_CLOCK_TIME_IS_VALID(running) && e->start == (int64_t)running)
        for (guint i = 0; i < e->n; i++)
          drops[n++] = (DcuEvent){0, e->frame[i], (int32_t)e->source[i], (int16_t)st->index, P_DROP, 2 /* qos */};
    }
    g_mutex_unlock(&h->lock);
  }
  GST_OBJECT_UNLOCK(element);
  if (n == 0) {
    atomic_fetch_add_explicit(&st->qos_unnamed, 1, memory_order_relaxed);
    return;
  }
  int64_t now = dcu_clock_ns(self->clock);
  for (guint i = 0; i < n; i++) drops[i].ts = now;
  dcu_push(self->ring, drops, n);
}

static void on_push_post(GObject *obj, GstClockTime t, GstPad *pad, GstFlowReturn res) {
  (void)obj; (void)t; (void)res;
  dcu_note_push_returned(pad);
  link_out_sent(pad);
}

/* --- parameters and life -------------------------------------------------------------------- */

static gboolean warn_unknown(GQuark field, const GValue *value, gpointer data) {
  (void)value; (void)data;
  const char *name = g_quark_to_string(field);
  for (int i = 0; KNOWN_PARAMS[i]; i++)
    if (strcmp(name, KNOWN_PARAMS[i]) == 0) return TRUE;
  g_printerr("dcuscope tracer: unknown parameter '%s' ignored (known: node, trace, clock, capacity, deepstream)\n",
             name);
  return TRUE;
}

static char *param_string(GstStructure *params, const char *key) {
  if (!params || !gst_structure_has_field(params, key)) return NULL;
  const GValue *v = gst_structure_get_value(params, key);
  return G_VALUE_HOLDS_STRING(v) ? g_value_dup_string(v) : gst_value_serialize(v);
}

static void register_pre_hooks(GstDcuscopeTracer *self) {
  GstTracer *tracer = GST_TRACER(self);
  if (!self->in_process) gst_tracing_register_hook(tracer, "element-post-message-pre", G_CALLBACK(on_message));
  gst_tracing_register_hook(tracer, "pad-push-pre", G_CALLBACK(on_push_pre));
  gst_tracing_register_hook(tracer, "pad-push-list-pre", G_CALLBACK(on_push_list_pre));
  /* Before 1.22 these names are unknown, and an unknown name registers a hook for every hook. */
  guint major, minor, micro, nano;
  gst_version(&major, &minor, &micro, &nano);
  self->chain_hooks = major > 1 || minor >= 22;
  if (self->chain_hooks) {
    gst_tracing_register_hook(tracer, "pad-chain-pre", G_CALLBACK(on_chain_pre));
    gst_tracing_register_hook(tracer, "pad-chain-list-pre", G_CALLBACK(on_chain_list_pre));
  }
  self->pre_hooks = TRUE;
}

static void register_post_hooks(GstDcuscopeTracer *self) {
  GstTracer *tracer = GST_TRACER(self);
  gst_tracing_register_hook(tracer, "pad-push-post", G_CALLBACK(on_push_post));
  gst_tracing_register_hook(tracer, "pad-push-list-post", G_CALLBACK(on_push_post));
}

static gboolean making_in_process;

static void gst_dcuscope_tracer_constructed(GObject *object) {
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)object;
  G_OBJECT_CLASS(gst_dcuscope_tracer_parent_class)->constructed(object);
  if (making_in_process) {
    /* The pads come from probes.tracer; the ring is its own; the push-post hook serves pad
     * probes and hook tracepoints alike. */
    self->in_process = TRUE;
    self->pad_quark = g_quark_from_static_string("dcuscope-in-process-pad");
    register_post_hooks(self);
    return;
  }
  char *text = NULL;
  g_object_get(object, "params", &text, NULL);
  GstStructure *params = NULL;
  if (text && *text) {
    char *full = g_strdup_printf("dcuscope,%s", text);
    params = gst_structure_from_string(full, NULL);
    g_free(full);
    if (!params) g_printerr("dcuscope tracer: cannot read parameters '%s'; using the defaults\n", text);
  }
  g_free(text);
  if (params) gst_structure_foreach(params, warn_unknown, NULL);

  char *node = param_string(params, "node");
  if (!node) node = g_strdup(g_get_host_name());
  char *trace = param_string(params, "trace");
  if (!trace) trace = g_strdup_printf("%s.trace.jsonl", node);
  char *clock = param_string(params, "clock");
  int which = 0;
  if (clock) {
    which = -1;
    for (int i = 0; i < 3; i++)
      if (strcmp(clock, CLOCK_NAMES[i]) == 0) which = i;
    if (which < 0) {
      g_printerr("dcuscope tracer: unknown clock '%s' (realtime, monotonic or tai); using realtime\n", clock);
      which = 0;
    }
  }
  g_free(clock);
  guint64 capacity = DEFAULT_CAPACITY;
  char *cap_text = param_string(params, "capacity");
  if (cap_text) {
    guint64 v = g_ascii_strtoull(cap_text, NULL, 10);
    if (v >= 1024) capacity = v;
    else g_printerr("dcuscope tracer: capacity '%s' is not a number of events >= 1024; using %d\n", cap_text, DEFAULT_CAPACITY);
    g_free(cap_text);
  }
  char *deepstream = param_string(params, "deepstream");
  self->deepstream = deepstream && (strcmp(deepstream, "1") == 0 || g_ascii_strcasecmp(deepstream, "true") == 0);
  g_free(deepstream);
  if (params) gst_structure_free(params);

  self->clock = CLOCK_IDS[which];
  self->ring = dcu_ring_new(capacity);
  self->writer = dcu_writer_start(self->ring, &self->graph, trace, node, CLOCK_NAMES[which], dcu_clock_ns(self->clock));
  g_free(node);
  g_free(trace);
  if (!self->writer) return; /* said why; trace nothing */
  g_atomic_pointer_set(&live_tracer, self);

  register_pre_hooks(self);
  register_post_hooks(self);
}


static void stop_writer(GstDcuscopeTracer *self) {
#if GLIB_CHECK_VERSION(2, 74, 0)
  DcuWriter *writer = g_atomic_pointer_exchange(&self->writer, NULL);
#else  /* GLib before 2.74 (Debian 11, Ubuntu 22.04: JetPack 6, DeepStream 7.1): the builtin it wraps */
  DcuWriter *writer = __atomic_exchange_n(&self->writer, NULL, __ATOMIC_SEQ_CST);
#endif
  if (writer) dcu_writer_stop(writer);
}

static void at_exit(void) {
  GstDcuscopeTracer *self = g_atomic_pointer_get(&live_tracer);
  if (self) stop_writer(self);
}

static void gst_dcuscope_tracer_finalize(GObject *object) {
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)object;
  g_atomic_pointer_compare_and_exchange(&live_tracer, self, NULL);
  stop_writer(self);
  /* Stages and the ring stay: pads of elements still alive point at them. */
  G_OBJECT_CLASS(gst_dcuscope_tracer_parent_class)->finalize(object);
}

static void gst_dcuscope_tracer_init(GstDcuscopeTracer *self) {
  g_mutex_init(&self->graph.lock);
  self->pad_quark = g_quark_from_static_string("dcuscope-tracer-pad");
  self->stage_quark = g_quark_from_static_string("dcuscope-tracer-stage");
  self->graph.stage_quark = self->stage_quark;
  self->graph.edges = g_malloc0(MAX_STAGES * MAX_STAGES);
  self->arrivals = g_new0(DcuArrivals, 1);
  g_mutex_init(&self->arrivals->lock);
  static gsize registered = 0;
  if (g_once_init_enter(&registered)) {
    atexit(at_exit);
    g_once_init_leave(&registered, 1);
  }
}

static void gst_dcuscope_tracer_class_init(GstDcuscopeTracerClass *klass) {
  GObjectClass *object_class = G_OBJECT_CLASS(klass);
  object_class->constructed = gst_dcuscope_tracer_constructed;
  object_class->finalize = gst_dcuscope_tracer_finalize;
}

GType dcu_plugin_tracer_type(void) { return gst_dcuscope_tracer_get_type(); }

/* --- a GST_TRACERS tracer made by a program itself (dcuscope run of a launch: config) -------- */

/* The tracer GST_TRACERS="dcuscope(PARAMS)" would make, made now: it traces what runs from now
 * on. NULL (and a line on stderr) when its trace file cannot be written. */
GstTracer *dcu_tracer_new(const char *params) {
  GstDcuscopeTracer *self = g_object_new(gst_dcuscope_tracer_get_type(), "params", params, NULL);
  if (!self->writer) {
    gst_object_unref(self);
    return NULL;
  }
  return GST_TRACER(self);
}

/* Close its trace (the end line); its hooks stay registered until gst_deinit but do nothing. */
void dcu_tracer_finish(GstTracer *tracer) {
  GstDcuscopeTracer *self = (GstDcuscopeTracer *)tracer;
  atomic_store(&self->finished, 1);
  stop_writer(self);
}

/* --- in process: the same tracer, on the pads probes.tracer chooses ------------------------- */

static GMutex in_process_lock;
static GstDcuscopeTracer *in_process;

/* The process's in-process tracer (made once, kept until gst_deinit), its pre hooks registered
 * when `pre` (hook tracepoints) asks for them: pad-probe tracepoints need only push-post. */
void dcu_in_process_tracer(gboolean pre) {
  g_mutex_lock(&in_process_lock);
  if (!in_process) {
    making_in_process = TRUE;
    in_process = g_object_new(gst_dcuscope_tracer_get_type(), NULL);
    making_in_process = FALSE;
  }
  if (pre && !in_process->pre_hooks) register_pre_hooks(in_process);
  g_mutex_unlock(&in_process_lock);
}

/* A tracepoint on pad fired by the tracer's hooks (instead of a pad probe); the same records. Point
 * P_LINK places a watch instead: on a link-out sink's sink pad, a depayloader's sink pad or a
 * source element's src pad, what links.h needs (an origin's frames then find where they came from). */
gulong dcu_hook_attach(DcuRing *ring, GstPad *pad, int stage, int point, int clock_id) {
  if (!ring || !GST_IS_PAD(pad)) return 0;
  dcu_in_process_tracer(TRUE);
  DcuPadInfo *info = g_new0(DcuPadInfo, 1);
  info->stamps = 0;
  info->source = -1;
  /* A watch (point P_LINK) records no tracepoint: it notes what crosses to or from another pipeline. */
  info->link_out = info->source_out = info->rtp_in = point == P_LINK ? -1 : 0;
  info->last_key = -1;
  dcu_probe_setup(&info->probe, ring, pad, stage, point, (clockid_t)clock_id);
  atomic_store(&info->active, 1);
  /* Replacing an earlier one frees it: only while no buffer flows (attach before PLAYING). */
  g_object_set_qdata_full(G_OBJECT(pad), in_process->pad_quark, info, pad_info_free);
  return 1;
}

/* Stop the pad's hook tracepoint. Its state stays until the pad is freed: a streaming thread
 * may be inside a hook with it right now. */
void dcu_hook_detach(GstPad *pad) {
  if (!in_process || !GST_IS_PAD(pad)) return;
  DcuPadInfo *info = g_object_get_qdata(G_OBJECT(pad), in_process->pad_quark);
  if (info) atomic_store(&info->active, 0);
}
