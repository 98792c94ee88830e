/* A GStreamer application that knows nothing of dcuscope, for the tracer tests: it runs a
 * gst-launch description to its end and, as ground truth taken in the same run, prints one line
 * per buffer that crosses a pad of each element named on the command line:
 *
 *   probe ELEMENT PAD PTS_NS CLOCK_REALTIME_NS
 *
 * It never calls gst_deinit(): the tracer must finish its trace when the process exits.
 *
 *   cc probed_app.c $(pkg-config --cflags --libs gstreamer-1.0) -o probed_app
 *   GST_TRACERS=dcuscope ./probed_app "videotestsrc num-buffers=10 ! identity name=id ! fakesink" id
 */
#include <gst/gst.h>
#include <stdio.h>
#include <time.h>

static GMutex out_lock;

static GstPadProbeReturn on_buffer(GstPad *pad, GstPadProbeInfo *info, gpointer data) {
  struct timespec t;
  clock_gettime(CLOCK_REALTIME, &t);
  GstBuffer *buf = GST_PAD_PROBE_INFO_BUFFER(info);
  gint64 pts = GST_BUFFER_PTS_IS_VALID(buf) ? (gint64)GST_BUFFER_PTS(buf) : -1;
  g_mutex_lock(&out_lock);
  printf("probe %s %s %" G_GINT64_FORMAT " %" G_GINT64_FORMAT "\n", (const char *)data, GST_PAD_NAME(pad), pts,
         (gint64)t.tv_sec * 1000000000LL + t.tv_nsec);
  g_mutex_unlock(&out_lock);
  return GST_PAD_PROBE_OK;
}

int main(int argc, char **argv) {
  gst_init(&argc, &argv);
  if (argc < 2) {
    fprintf(stderr, "usage: %s DESCRIPTION [ELEMENT ...]\n", argv[0]);
    return 2;
  }
  GError *error = NULL;
  GstElement *pipeline = gst_parse_launch(argv[1], &error);
  if (!pipeline) {
    fprintf(stderr, "%s\n", error->message);
    return 2;
  }
  for (int i = 2; i < argc; i++) {
    GstElement *element = gst_bin_get_by_name(GST_BIN(pipeline), argv[i]);
    if (!element) {
      fprintf(stderr, "no element %s\n", argv[i]);
      return 2;
    }
    for (GList *l = element->pads; l; l = l->next)
      gst_pad_add_probe(GST_PAD(l->data), GST_PAD_PROBE_TYPE_BUFFER, on_buffer, argv[i], NULL);
    gst_object_unref(element);
  }
  gst_element_set_state(pipeline, GST_STATE_PLAYING);
  GstBus *bus = gst_element_get_bus(pipeline);
  GstMessage *msg = gst_bus_timed_pop_filtered(bus, 60 * GST_SECOND, GST_MESSAGE_EOS | GST_MESSAGE_ERROR);
  int status = (msg && GST_MESSAGE_TYPE(msg) == GST_MESSAGE_EOS) ? 0 : 1;
  if (status) fprintf(stderr, "the pipeline did not reach end-of-stream\n");
  if (msg) gst_message_unref(msg);
  gst_object_unref(bus);
  gst_element_set_state(pipeline, GST_STATE_NULL);
  gst_object_unref(pipeline);
  fflush(stdout);
  return status;
}
