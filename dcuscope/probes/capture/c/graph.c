/* Walking the pipeline's graph (graph.h). */

#include "graph.h"

GstElement *dcu_downstream_element(GstPad *src) {
  GstPad *peer = gst_pad_get_peer(src);
  for (int depth = 0; peer && GST_IS_PROXY_PAD(peer) && depth < 32; depth++) {
    GstProxyPad *internal = gst_proxy_pad_get_internal(GST_PROXY_PAD(peer));
    gst_object_unref(peer);
    peer = internal ? gst_pad_get_peer(GST_PAD(internal)) : NULL;
    if (internal) gst_object_unref(internal);
  }
  if (!peer) return NULL;
  GstElement *owner = gst_pad_get_parent_element(peer);
  gst_object_unref(peer);
  if (owner && GST_IS_BIN(owner)) {
    gst_object_unref(owner);
    return NULL;
  }
  return owner;
}
