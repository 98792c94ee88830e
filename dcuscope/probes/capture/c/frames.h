/* The frames meta (frames.c): which frames a buffer carries, as plugins/frames.py writes and reads
 * it. The bottom of the native library: it includes only GStreamer.
 *
 * A GstReferenceTimestampMeta whose caps are named "timestamp/x-dcuscope-frames", fields "source"
 * (int), "frame" and "origin" (guint64): lists of n entries, or plain fields when n is 1. */
#ifndef DCU_FRAMES_H
#define DCU_FRAMES_H

#include <gst/gst.h>
#include <stdint.h>

#define FRAMES_MEDIA_TYPE "timestamp/x-dcuscope-frames"

/* Interned by dcu_frames_init: comparing quarks is an integer compare. */
G_GNUC_INTERNAL extern GQuark dcu_frames_quark, dcu_source_quark, dcu_frame_quark, dcu_origin_quark;

/* Intern the quarks (once; any thread). Every function here needs it first. */
void dcu_frames_init(void);

/* The frames meta of buf: its structure, or NULL. */
const GstStructure *dcu_frames_structure(GstBuffer *buf);
/* Entry i of the meta's (source, frame) lists, n = their length. */
guint dcu_frames_count(const GstStructure *s);
void dcu_frames_get(const GstStructure *s, guint i, int64_t *source, int64_t *frame);
/* The origin (ns) of entry i, 0 when the meta has none. */
int64_t dcu_frames_origin(const GstStructure *s, guint i);
/* A new frames structure of n entries. */
GstStructure *dcu_frames_new(guint n, const int64_t *sources, const int64_t *frames, const int64_t *origins);

/* For loops over a meta's lists on the streaming thread (the ring's recording): inline. */
static inline gboolean dcu_value_i64(const GValue *v, int64_t *out) {
  switch (G_TYPE_FUNDAMENTAL(G_VALUE_TYPE(v))) {
    case G_TYPE_INT: *out = g_value_get_int(v); return TRUE;
    case G_TYPE_UINT: *out = g_value_get_uint(v); return TRUE;
    case G_TYPE_INT64: *out = g_value_get_int64(v); return TRUE;
    case G_TYPE_UINT64: *out = (int64_t)g_value_get_uint64(v); return TRUE;
    default: return FALSE;
  }
}

/* Element i of a field that is an array, or the field itself when it is a scalar. */
static inline const GValue *dcu_field_item(const GValue *field, guint i) {
  return GST_VALUE_HOLDS_ARRAY(field) ? gst_value_array_get_value(field, i) : field;
}

static inline guint dcu_field_size(const GValue *field) {
  return GST_VALUE_HOLDS_ARRAY(field) ? gst_value_array_get_size(field) : 1;
}

#endif
