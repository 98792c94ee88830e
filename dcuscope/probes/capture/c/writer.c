/* The tracer's own thread: drains the ring into a trace file of format 3 (probes/trace/tracefile.py),
 * without Python, so that any process can be traced.
 *
 * Stages are numbered in the file as they first carry frames, in graph order among those found
 * together (sources before what they feed). The header is the file's first line, padded with
 * spaces to HEADER_BYTES: when a stage, a source or a lineage note appears later (decodebin
 * adds elements while playing) the line is rewritten in place, and a reader that opens the
 * file at any time reads a header that names every stage its events use. Every line is flushed
 * as it is written; the end line comes from dcu_writer_stop (gst_deinit or process exit).
 */

#include "writer.h"

#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <stddef.h>
#include <unistd.h>

#define HEADER_BYTES 65536
#define DRAIN_EVENTS 65536
#define PERIOD_US 50000

struct DcuWriter {
  DcuRing *ring;
  DcuGraph *graph;
  FILE *file;
  char *path, *node, *clock;
  int64_t started_ns;
  GThread *thread;
  GMutex lock;
  GCond cond;
  gboolean stop;
  int out_of[MAX_STAGES];      /* internal stage -> its number in the file, -1 not yet */
  int internal_of[MAX_STAGES]; /* and back */
  int n_out;
  int header_version;          /* graph version the header shows; -1 none written */
  gboolean header_full;        /* the header did not fit: stages found later are left out */
  uint64_t events, skipped;
  DcuEvent *batch;
};

static void json_string(GString *out, const char *s) {
  g_string_append_c(out, '"');
  for (const unsigned char *p = (const unsigned char *)s; *p; p++) {
    if (*p == '"' || *p == '\\') g_string_append_printf(out, "\\%c", *p);
    else if (*p < 0x20) g_string_append_printf(out, "\\u%04x", *p);
    else g_string_append_c(out, (char)*p);
  }
  g_string_append_c(out, '"');
}

/* edges[a * MAX_STAGES + b]: stage a feeds stage b (internal indices, stages 0..n-1): the links
 * the tracer saw carry buffers, and those of the elements still alive now. */
static void find_links(DcuGraph *g, int n, guint8 *edges) {
  g_mutex_lock(&g->lock);
  memcpy(edges, g->edges, MAX_STAGES * MAX_STAGES);
  g_mutex_unlock(&g->lock);
  for (int a = 0; a < n; a++) {
    GstElement *element = g_weak_ref_get(&g->stages[a]->element);
    if (!element) continue;
    GstIterator *it = gst_element_iterate_src_pads(element);
    GValue item = G_VALUE_INIT;
    gboolean more = TRUE;
    while (more) {
      switch (gst_iterator_next(it, &item)) {
        case GST_ITERATOR_OK: {
          GstElement *next = dcu_downstream_element(GST_PAD(g_value_get_object(&item)));
          DcuStage *b = next ? g_object_get_qdata(G_OBJECT(next), g->stage_quark) : NULL;
          if (b && b->index < n) edges[a * MAX_STAGES + b->index] = 1;
          if (next) gst_object_unref(next);
          g_value_reset(&item);
          break;
        }
        case GST_ITERATOR_RESYNC: gst_iterator_resync(it); break;
        default: more = FALSE;
      }
    }
    g_value_unset(&item);
    gst_iterator_free(it);
    gst_object_unref(element);
  }
}

/* Number the stages in `wanted` (internal indices) after those already numbered: upstream
 * first, each branch whole before the next (depth first), lower indices first among equals. */
static void place(DcuWriter *w, const guint8 *wanted, int n, const guint8 *edges) {
  int indegree[MAX_STAGES] = {0}, stack[MAX_STAGES], top = 0;
  for (int a = 0; a < n; a++)
    for (int b = 0; b < n; b++)
      if (wanted[a] && wanted[b] && a != b && edges[a * MAX_STAGES + b]) indegree[b]++;
  for (int a = n - 1; a >= 0; a--)
    if (wanted[a] && indegree[a] == 0) stack[top++] = a;
  guint8 done[MAX_STAGES] = {0};
  while (top > 0) {
    int a = stack[--top];
    done[a] = 1;
    w->out_of[a] = w->n_out;
    w->internal_of[w->n_out++] = a;
    for (int b = n - 1; b >= 0; b--)
      if (wanted[b] && b != a && edges[a * MAX_STAGES + b] && --indegree[b] == 0) stack[top++] = b;
  }
  for (int a = 0; a < n; a++) /* a cycle: the rest in the order found */
    if (wanted[a] && !done[a]) {
      w->out_of[a] = w->n_out;
      w->internal_of[w->n_out++] = a;
    }
}

/* The header line (graph lock held). */
static GString *header_json(DcuWriter *w, const guint8 *edges) {
  DcuGraph *g = w->graph;
  GString *h = g_string_new("{\"dcuscope_trace\":3,\"header\":{\"node\":");
  json_string(h, w->node);
  g_string_append(h, ",\"clock\":");
  json_string(h, w->clock);
  g_string_append(h, ",\"stages\":[");
  for (int i = 0; i < w->n_out; i++) {
    if (i) g_string_append_c(h, ',');
    json_string(h, g->stages[w->internal_of[i]]->name);
  }
  g_string_append(h, "],\"sources\":{");
  for (int i = 0; i < g->n_sources; i++) {
    g_string_append_printf(h, "%s\"%d\":", i ? "," : "", i);
    json_string(h, g->sources[i]);
  }
  g_string_append_printf(h, "},\"started_ns\":%" G_GINT64_FORMAT ",\"versions\":{\"gstreamer\":", w->started_ns);
  char *version = gst_version_string();
  json_string(h, version);
  g_free(version);
  g_string_append(h, ",\"probes\":\"tracer\"},\"format\":3,\"kinds\":{");
  for (int i = 0; i < w->n_out; i++) {
    DcuStage *st = g->stages[w->internal_of[i]];
    if (i) g_string_append_c(h, ',');
    json_string(h, st->name);
    g_string_append_c(h, ':');
    json_string(h, st->factory);
  }
  g_string_append(h, "},\"links\":[");
  gboolean first = TRUE;
  for (int i = 0; i < w->n_out; i++)
    for (int j = 0; j < w->n_out; j++)
      if (edges[w->internal_of[i] * MAX_STAGES + w->internal_of[j]]) {
        g_string_append_printf(h, "%s[%d,%d]", first ? "" : ",", i, j);
        first = FALSE;
      }
  g_string_append(h, "],\"lineage_unknown\":[");
  first = TRUE;
  for (int i = 0; i < w->n_out; i++) {
    DcuStage *st = g->stages[w->internal_of[i]];
    if (!(atomic_load(&st->entered) && !atomic_load(&st->pushed_identified) && atomic_load(&st->unidentified_out) >= LINEAGE_LOST_AFTER))
      continue;
    if (!first) g_string_append_c(h, ',');
    json_string(h, st->name);
    first = FALSE;
  }
  g_string_append(h, "]}}");
  return h;
}

/* Number the stages these events use, and (re)write the header if anything changed. */
static void update_header(DcuWriter *w, const DcuEvent *events, uint64_t n) {
  DcuGraph *g = w->graph;
  guint8 wanted[MAX_STAGES] = {0};
  gboolean new_stages = FALSE;
  for (uint64_t i = 0; i < n; i++) {
    int s = events[i].stage;
    if (s >= 0 && s < MAX_STAGES && w->out_of[s] < 0 && !w->header_full) wanted[s] = new_stages = TRUE;
  }
  int version = atomic_load(&g->version);
  if (!new_stages && version == w->header_version) return;
  guint8 *edges = g_malloc0(MAX_STAGES * MAX_STAGES);
  g_mutex_lock(&g->lock);
  int n_stages = g->n_stages;
  g_mutex_unlock(&g->lock);
  find_links(g, n_stages, edges); /* takes pad locks: not under the graph lock */
  g_mutex_lock(&g->lock);
  int before = w->n_out;
  int saved_out[MAX_STAGES];
  memcpy(saved_out, w->out_of, sizeof(saved_out));
  if (new_stages) place(w, wanted, n_stages, edges);
  GString *h = header_json(w, edges);
  g_mutex_unlock(&g->lock);
  g_free(edges);
  if (h->len >= HEADER_BYTES) {
    g_printerr("dcuscope tracer: %s: the trace header would exceed %d bytes; stages found from now on are left out\n",
               w->path, HEADER_BYTES);
    memcpy(w->out_of, saved_out, sizeof(saved_out));
    w->n_out = before;
    w->header_full = TRUE;
    g_string_free(h, TRUE);
    return;
  }
  while (h->len < HEADER_BYTES - 1) g_string_append_c(h, ' ');
  g_string_append_c(h, '\n');
  fflush(w->file);
  if (pwrite(fileno(w->file), h->str, h->len, 0) != (ssize_t)h->len)
    g_printerr("dcuscope tracer: %s: cannot write the trace header: %s\n", w->path, g_strerror(errno));
  if (w->header_version < 0) fseeko(w->file, HEADER_BYTES, SEEK_SET);
  w->header_version = version;
  g_string_free(h, TRUE);
}

/* Decimal digits of v at p, returns the end (printf is 3x slower, and this thread must keep up
 * with every streaming thread of the process together). */
static char *put_int(char *p, int64_t v) {
  char tmp[24];
  int n = 0;
  uint64_t u = v < 0 ? (uint64_t)(-(v + 1)) + 1 : (uint64_t)v;
  if (v < 0) *p++ = '-';
  do {
    tmp[n++] = (char)('0' + u % 10);
    u /= 10;
  } while (u);
  while (n) *p++ = tmp[--n];
  return p;
}

static void write_events(DcuWriter *w, const DcuEvent *events, uint64_t n) {
  char line[8192];
  char *p = line;
  gboolean open = FALSE;
  for (uint64_t i = 0; i < n; i++) {
    const DcuEvent *e = &events[i];
    int out = (e->stage >= 0 && e->stage < MAX_STAGES) ? w->out_of[e->stage] : -1;
    if (out < 0) {
      w->skipped++;
      continue;
    }
    if (p - line > (ptrdiff_t)sizeof(line) - 128) {
      fwrite(line, 1, (size_t)(p - line), w->file);
      p = line;
    }
    if (open) *p++ = ',';
    else {
      memcpy(p, "{\"events\":[", 11);
      p += 11;
    }
    *p++ = '[';
    p = put_int(p, e->ts);
    *p++ = ',';
    p = put_int(p, out);
    *p++ = ',';
    p = put_int(p, e->point);
    *p++ = ',';
    p = put_int(p, e->source);
    *p++ = ',';
    p = put_int(p, e->frame);
    *p++ = ',';
    p = put_int(p, e->code);
    *p++ = ']';
    open = TRUE;
    w->events++;
  }
  if (open) {
    memcpy(p, "]}\n", 3);
    p += 3;
    fwrite(line, 1, (size_t)(p - line), w->file);
    fflush(w->file);
  }
}

static void drain_all(DcuWriter *w) {
  for (;;) {
    uint64_t n = dcu_drain(w->ring, w->batch, DRAIN_EVENTS);
    update_header(w, w->batch, n);
    write_events(w, w->batch, n);
    if (n < DRAIN_EVENTS) return;
  }
}

static gpointer writer_main(gpointer data) {
  DcuWriter *w = data;
  g_mutex_lock(&w->lock);
  while (!w->stop) {
    gint64 until = g_get_monotonic_time() + PERIOD_US;
    g_cond_wait_until(&w->cond, &w->lock, until);
    if (w->stop) break;
    g_mutex_unlock(&w->lock);
    drain_all(w);
    g_mutex_lock(&w->lock);
  }
  g_mutex_unlock(&w->lock);
  return NULL;
}

DcuWriter *dcu_writer_start(DcuRing *ring, DcuGraph *graph, const char *path, const char *node,
                            const char *clock_name, int64_t started_ns) {
  FILE *file = fopen(path, "w");
  if (!file) {
    g_printerr("dcuscope tracer: cannot write the trace file %s: %s; tracing is off\n", path, g_strerror(errno));
    return NULL;
  }
  DcuWriter *w = g_new0(DcuWriter, 1);
  w->ring = ring;
  w->graph = graph;
  w->file = file;
  w->path = g_strdup(path);
  w->node = g_strdup(node);
  w->clock = g_strdup(clock_name);
  w->started_ns = started_ns;
  w->header_version = -1;
  for (int i = 0; i < MAX_STAGES; i++) w->out_of[i] = -1;
  w->batch = g_new(DcuEvent, DRAIN_EVENTS);
  g_mutex_init(&w->lock);
  g_cond_init(&w->cond);
  w->thread = g_thread_new("dcuscope-trace", writer_main, w);
  return w;
}

void dcu_writer_stop(DcuWriter *w) {
  g_mutex_lock(&w->lock);
  w->stop = TRUE;
  g_cond_signal(&w->cond);
  g_mutex_unlock(&w->lock);
  g_thread_join(w->thread);
  drain_all(w);
  if (w->header_version < 0) {
    atomic_fetch_add(&w->graph->version, 1);
    update_header(w, NULL, 0); /* nothing traced: the header still says who and when */
  }
  uint64_t dropped = 0;
  dcu_stats(w->ring, NULL, &dropped, NULL);
  DcuGraph *g = w->graph;
  g_mutex_lock(&g->lock);
  for (int i = 0; i < g->n_stages; i++) {
    uint64_t unnamed = atomic_load(&g->stages[i]->qos_unnamed);
    if (unnamed)
      g_printerr("dcuscope tracer: %s dropped %" G_GUINT64_FORMAT " buffers for QoS before it was watched: "
                 "their frames are not named in the trace\n", g->stages[i]->name, unnamed);
    uint64_t shared = atomic_load(&g->stages[i]->shared);
    if (shared)
      g_printerr("dcuscope tracer: %" G_GUINT64_FORMAT " frames leaving %s have no identity: their buffers were "
                 "shared (not writable) where they should get one\n", shared, g->stages[i]->name);
  }
  g_mutex_unlock(&g->lock);
  fprintf(w->file, "{\"end\":{\"events\":%" G_GUINT64_FORMAT ",\"dropped\":%" G_GUINT64_FORMAT "}}\n", w->events,
          dropped + w->skipped);
  fclose(w->file);
  g_mutex_clear(&w->lock);
  g_cond_clear(&w->cond);
  g_free(w->batch);
  g_free(w->path);
  g_free(w->node);
  g_free(w->clock);
  g_free(w);
}
