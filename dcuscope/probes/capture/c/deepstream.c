/* DeepStream's batch metadata read by the dcuscope tracer, without NVIDIA's headers or libraries.
 *
 * nvstreammux attaches to each batch an NvDsMeta (the GstMeta API registered as "NvDsMetaAPI",
 * found by that name at run time: nothing links to DeepStream) whose meta_data is an
 * NvDsBatchMeta when its meta_type is NVDS_BATCH_GST_META; the batch meta's frame_meta_list
 * holds one NvDsFrameMeta per frame, with the frame's source_id (the camera) and frame_num
 * (counted per source by nvstreammux). The structs below mirror the leading fields of
 * nvdsmeta.h and gstnvdsmeta.h as DeepStream 6.x and 7.x publish them, on 64-bit Linux.
 *
 * UNTESTED with DeepStream: no NVIDIA software can be installed where dcuscope is developed.
 * The tests attach metas laid out as these structs say (tests/probes/capture/data/fake_nvds.c), which
 * checks the tracer's use of them, not the layout against NVIDIA's. So the tracer reads them only
 * when asked: GST_TRACERS="dcuscope(deepstream=1)". docs/tracer.md says what to check first.
 */

#include "deepstream.h"

#define NVDS_GST_CUSTOM_META 4096
#define NVDS_BATCH_GST_META (NVDS_GST_CUSTOM_META + 1)
#define MAX_BATCH 1024

typedef struct {
  GstMeta meta;
  gpointer meta_data;
  gpointer user_data;
  gint meta_type;
} DsMeta;

typedef struct {
  void *batch_meta;
  int meta_type;
  void *user_context;
  void *copy_func;
  void *release_func;
} DsBaseMeta;

typedef struct {
  DsBaseMeta base_meta;
  guint max_frames_in_batch;
  guint num_frames_in_batch;
  void *pools[6]; /* frame, object, classifier, display, user and label-info meta pools */
  GList *frame_meta_list;
} DsBatchMeta;

typedef struct {
  DsBaseMeta base_meta;
  guint pad_index;
  guint batch_id;
  gint frame_num;
  guint64 buf_pts;
  guint64 ntp_timestamp;
  guint source_id;
} DsFrameMeta;

_Static_assert(G_STRUCT_OFFSET(DsBatchMeta, frame_meta_list) == 96, "NvDsBatchMeta.frame_meta_list at 96 (LP64)");
_Static_assert(G_STRUCT_OFFSET(DsFrameMeta, frame_num) == 48, "NvDsFrameMeta.frame_num at 48 (LP64)");
_Static_assert(G_STRUCT_OFFSET(DsFrameMeta, source_id) == 72, "NvDsFrameMeta.source_id at 72 (LP64)");

/* The frames of buf's NvDsBatchMeta as a frames structure (origin `now`), or NULL. */
GstStructure *dcu_deepstream_frames(GstBuffer *buf, int64_t now) {
  static GType api = 0;
  if (G_UNLIKELY(!api)) {
    api = g_type_from_name("NvDsMetaAPI"); /* registered once DeepStream's meta library is loaded */
    if (!api) return NULL;
  }
  gpointer state = NULL;
  GstMeta *meta;
  while ((meta = gst_buffer_iterate_meta_filtered(buf, &state, api))) {
    DsMeta *ds = (DsMeta *)meta;
    if (ds->meta_type != NVDS_BATCH_GST_META || !ds->meta_data) continue;
    DsBatchMeta *batch = ds->meta_data;
    int64_t sources[MAX_BATCH], frames[MAX_BATCH], origins[MAX_BATCH];
    guint n = 0;
    for (GList *l = batch->frame_meta_list; l && n < MAX_BATCH; l = l->next, n++) {
      DsFrameMeta *frame = l->data;
      sources[n] = frame->source_id;
      frames[n] = frame->frame_num < 0 ? 0 : frame->frame_num;
      origins[n] = now;
    }
    return n ? dcu_frames_new(n, sources, frames, origins) : NULL;
  }
  return NULL;
}
