/* Tracepoints fired by pad probes (padprobe.h): one native probe per traced pad, recording
 * through the ring (ring.h). Service and wait need to know when a pad's push returned, which
 * only the tracer's push-post hook tells: attaching makes sure the in-process tracer is there
 * (tracer.h) without its pre hooks, which the probes replace. */

#include "padprobe.h"

#include "tracer.h"

static GstPadProbeReturn on_probe(GstPad *pad, GstPadProbeInfo *info, gpointer user_data) {
  (void)pad;
  DcuProbe *p = user_data;
  struct timespec t;
  clock_gettime(p->clock, &t);
  int64_t ts = (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
  if (GST_PAD_PROBE_INFO_TYPE(info) & GST_PAD_PROBE_TYPE_BUFFER) {
    dcu_record_buffer(p, GST_PAD_PROBE_INFO_BUFFER(info), ts);
  } else if (GST_PAD_PROBE_INFO_TYPE(info) & GST_PAD_PROBE_TYPE_BUFFER_LIST) {
    GstBufferList *list = GST_PAD_PROBE_INFO_BUFFER_LIST(info);
    guint len = gst_buffer_list_length(list);
    for (guint i = 0; i < len; i++) dcu_record_buffer(p, gst_buffer_list_get(list, i), ts);
  }
  return GST_PAD_PROBE_OK;
}

static void probe_free(gpointer data) {
  DcuProbe *p = data;
  dcu_probe_clear(p);
  g_free(p);
}

/* Add a tracepoint on pad; returns the probe id (0 when pad is not a GstPad). The probe holds
 * a reference on the ring until it is removed. */
gulong dcu_attach(DcuRing *ring, GstPad *pad, int stage, int point, int clock_id) {
  if (!ring || !GST_IS_PAD(pad)) return 0;
  dcu_in_process_tracer(FALSE);
  GstPadProbeType types = GST_PAD_PROBE_TYPE_BUFFER | GST_PAD_PROBE_TYPE_BUFFER_LIST;
  /* Such a pad would see a list twice: whole, then buffer by buffer. Keep the per-buffer
   * probes only, which also time each buffer's own entry. */
  if (dcu_pad_splits_lists(pad)) types = GST_PAD_PROBE_TYPE_BUFFER;
  DcuProbe *p = g_new0(DcuProbe, 1);
  dcu_probe_setup(p, ring, pad, stage, point, (clockid_t)clock_id);
  return gst_pad_add_probe(pad, types, on_probe, p, probe_free);
}

void dcu_detach(GstPad *pad, gulong probe_id) {
  if (GST_IS_PAD(pad) && probe_id) gst_pad_remove_probe(pad, probe_id);
}

