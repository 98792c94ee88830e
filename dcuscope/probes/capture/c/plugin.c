/* The native library as a GStreamer plugin: it registers the "dcuscope" tracer factory and
 * nothing else (the tracer itself: tracer.c).
 *
 *   GST_PLUGIN_PATH="$(dcuscope plugin-path)" GST_TRACERS="dcuscope(node=DCU-1)" gst-launch-1.0 ...
 */
#include "tracer.h"

static gboolean plugin_init(GstPlugin *plugin) {
  return gst_tracer_register(plugin, "dcuscope", dcu_plugin_tracer_type());
}

#define PACKAGE "dcuscope"
GST_PLUGIN_DEFINE(GST_VERSION_MAJOR, GST_VERSION_MINOR, dcuscope,
                  "dcuscope: per-frame stage delays, service and wait of any pipeline",
                  plugin_init, "0.1", "MIT/X11", "dcuscope", "https://github.com/dcuscope/dcuscope")
