/* Batches that carry metadata laid out as DeepStream's NvDsMeta / NvDsBatchMeta / NvDsFrameMeta
 * (nvdsmeta.h, gstnvdsmeta.h of DeepStream 6.x-7.x, 64-bit), under the GstMeta API name
 * "NvDsMetaAPI", for the tracer's deepstream=1 path. No NVIDIA code: this checks how the tracer
 * uses such metas, not that NVIDIA's layout is the one written here (docs/tracer.md).
 *
 *   fake_nvds BATCHES
 * pushes BATCHES buffers, each a batch of frame k of cameras 3 and 7, through
 *   appsrc name=mux ! identity name=infer sleep-time=1000 ! fakesink name=sink
 */
#include <gst/app/gstappsrc.h>
#include <gst/gst.h>
#include <stdlib.h>

#define NVDS_BATCH_GST_META (4096 + 1)

typedef struct {
  GstMeta meta;
  gpointer meta_data;
  gpointer user_data;
  gint meta_type;
} NvDsMeta;

typedef struct {
  void *batch_meta;
  int meta_type;
  void *user_context;
  void *copy_func;
  void *release_func;
} NvDsBaseMeta;

typedef struct {
  NvDsBaseMeta base_meta;
  guint max_frames_in_batch;
  guint num_frames_in_batch;
  void *pools[6];
  GList *frame_meta_list;
} NvDsBatchMeta;

typedef struct {
  NvDsBaseMeta base_meta;
  guint pad_index;
  guint batch_id;
  gint frame_num;
  guint64 buf_pts;
  guint64 ntp_timestamp;
  guint source_id;
} NvDsFrameMeta;

static GType api_type(void) {
  static GType type = 0;
  static const gchar *tags[] = {NULL};
  if (!type) type = gst_meta_api_type_register("NvDsMetaAPI", tags);
  return type;
}

static gboolean meta_init(GstMeta *meta, gpointer params, GstBuffer *buffer) {
  (void)params; (void)buffer;
  NvDsMeta *m = (NvDsMeta *)meta;
  m->meta_data = NULL;
  m->user_data = NULL;
  m->meta_type = 0;
  return TRUE;
}

static void meta_free(GstMeta *meta, GstBuffer *buffer) {
  (void)buffer;
  NvDsBatchMeta *batch = ((NvDsMeta *)meta)->meta_data;
  if (batch) {
    g_list_free_full(batch->frame_meta_list, g_free);
    g_free(batch);
  }
}

static const GstMetaInfo *meta_info(void) {
  static const GstMetaInfo *info = NULL;
  if (!info) info = gst_meta_register(api_type(), "NvDsMeta", sizeof(NvDsMeta), meta_init, meta_free, NULL);
  return info;
}

static GstBuffer *batch(int k) {
  static const guint cameras[] = {3, 7};
  GstBuffer *buf = gst_buffer_new_allocate(NULL, 64, NULL);
  GST_BUFFER_PTS(buf) = (GstClockTime)k * GST_SECOND / 30;
  GST_BUFFER_DURATION(buf) = GST_SECOND / 30;
  NvDsBatchMeta *b = g_new0(NvDsBatchMeta, 1);
  for (guint i = 0; i < 2; i++) {
    NvDsFrameMeta *f = g_new0(NvDsFrameMeta, 1);
    f->base_meta.batch_meta = b;
    f->pad_index = i;
    f->batch_id = i;
    f->frame_num = k;
    f->source_id = cameras[i];
    b->frame_meta_list = g_list_append(b->frame_meta_list, f);
  }
  b->num_frames_in_batch = b->max_frames_in_batch = 2;
  NvDsMeta *m = (NvDsMeta *)gst_buffer_add_meta(buf, meta_info(), NULL);
  m->meta_data = b;
  m->meta_type = NVDS_BATCH_GST_META;
  return buf;
}

int main(int argc, char **argv) {
  gst_init(&argc, &argv);
  int batches = argc > 1 ? atoi(argv[1]) : 30;
  GstElement *pipeline = gst_parse_launch(
      "appsrc name=mux format=time caps=application/x-fake-batch ! identity name=infer sleep-time=1000 ! "
      "fakesink name=sink", NULL);
  GstElement *src = gst_bin_get_by_name(GST_BIN(pipeline), "mux");
  gst_element_set_state(pipeline, GST_STATE_PLAYING);
  for (int k = 0; k < batches; k++) gst_app_src_push_buffer(GST_APP_SRC(src), batch(k));
  gst_app_src_end_of_stream(GST_APP_SRC(src));
  GstBus *bus = gst_element_get_bus(pipeline);
  GstMessage *msg = gst_bus_timed_pop_filtered(bus, 30 * GST_SECOND, GST_MESSAGE_EOS | GST_MESSAGE_ERROR);
  int status = msg && GST_MESSAGE_TYPE(msg) == GST_MESSAGE_EOS ? 0 : 1;
  if (msg) gst_message_unref(msg);
  gst_object_unref(bus);
  gst_object_unref(src);
  gst_element_set_state(pipeline, GST_STATE_NULL);
  gst_object_unref(pipeline);
  gst_deinit();
  return status;
}
