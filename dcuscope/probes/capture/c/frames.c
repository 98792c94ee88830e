/* The frames meta: read a buffer's frames, make a frames structure (frames.h). */

#include "frames.h"

GQuark dcu_frames_quark, dcu_source_quark, dcu_frame_quark, dcu_origin_quark;
static gsize init_done = 0;

void dcu_frames_init(void) {
  if (g_once_init_enter(&init_done)) {
    dcu_frames_quark = g_quark_from_static_string(FRAMES_MEDIA_TYPE);
    dcu_source_quark = g_quark_from_static_string("source");
    dcu_frame_quark = g_quark_from_static_string("frame");
    dcu_origin_quark = g_quark_from_static_string("origin");
    g_once_init_leave(&init_done, 1);
  }
}

const GstStructure *dcu_frames_structure(GstBuffer *buf) {
  gpointer state = NULL;
  GstMeta *meta;
  while ((meta = gst_buffer_iterate_meta_filtered(buf, &state, GST_REFERENCE_TIMESTAMP_META_API_TYPE))) {
    GstCaps *ref = ((GstReferenceTimestampMeta *)meta)->reference;
    if (ref && gst_caps_get_size(ref) > 0) {
      const GstStructure *s = gst_caps_get_structure(ref, 0);
      if (gst_structure_get_name_id(s) == dcu_frames_quark) return s;
    }
  }
  return NULL;
}

guint dcu_frames_count(const GstStructure *s) {
  const GValue *sources = gst_structure_id_get_value(s, dcu_source_quark);
  const GValue *frames = gst_structure_id_get_value(s, dcu_frame_quark);
  return (sources && frames) ? MIN(dcu_field_size(sources), dcu_field_size(frames)) : 0;
}

void dcu_frames_get(const GstStructure *s, guint i, int64_t *source, int64_t *frame) {
  *source = *frame = -1;
  dcu_value_i64(dcu_field_item(gst_structure_id_get_value(s, dcu_source_quark), i), source);
  dcu_value_i64(dcu_field_item(gst_structure_id_get_value(s, dcu_frame_quark), i), frame);
}

int64_t dcu_frames_origin(const GstStructure *s, guint i) {
  const GValue *origins = gst_structure_id_get_value(s, dcu_origin_quark);
  int64_t origin = 0;
  if (origins && i < dcu_field_size(origins)) dcu_value_i64(dcu_field_item(origins, i), &origin);
  return origin;
}

static void append_item(GValue *array, GType type, int64_t v) {
  GValue item = G_VALUE_INIT;
  g_value_init(&item, type);
  if (type == G_TYPE_INT) g_value_set_int(&item, (int)v);
  else g_value_set_uint64(&item, (guint64)v);
  gst_value_array_append_value(array, &item);
  g_value_unset(&item);
}

GstStructure *dcu_frames_new(guint n, const int64_t *sources, const int64_t *frames, const int64_t *origins) {
  if (n == 1) /* one frame (a source's): plain fields, no lists to allocate */
    return gst_structure_new_id(dcu_frames_quark, dcu_source_quark, G_TYPE_INT, (int)sources[0], dcu_frame_quark, G_TYPE_UINT64,
                                (guint64)frames[0], dcu_origin_quark, G_TYPE_UINT64,
                                (guint64)(origins[0] > 0 ? origins[0] : 0), NULL);
  GValue lists[3] = {G_VALUE_INIT, G_VALUE_INIT, G_VALUE_INIT};
  for (int k = 0; k < 3; k++) g_value_init(&lists[k], GST_TYPE_ARRAY);
  for (guint i = 0; i < n; i++) {
    append_item(&lists[0], G_TYPE_INT, sources[i]);
    append_item(&lists[1], G_TYPE_UINT64, frames[i]);
    append_item(&lists[2], G_TYPE_UINT64, origins[i] > 0 ? origins[i] : 0);
  }
  GstStructure *s = gst_structure_new_id_empty(dcu_frames_quark);
  gst_structure_id_take_value(s, dcu_source_quark, &lists[0]);
  gst_structure_id_take_value(s, dcu_frame_quark, &lists[1]);
  gst_structure_id_take_value(s, dcu_origin_quark, &lists[2]);
  return s;
}
