/* The dcuscope GStreamer tracer (tracer.c): as GST_TRACERS loads it (plugin.c), made by a program
 * itself (dcu_tracer_new), or in process on the pads probes/capture/tracer.py chooses. Above
 * ring.h, frames.h, graph.h, deepstream.h and writer.h. */
#ifndef DCU_TRACER_H
#define DCU_TRACER_H

#include "ring.h"

/* The tracer's GType, which the plugin registers as "dcuscope". */
GType dcu_plugin_tracer_type(void);

/* A tracer as GST_TRACERS="dcuscope(PARAMS)" would make it: every pipeline from now on traced,
 * its trace file written by its own thread. dcu_tracer_finish writes the end line and frees it. */
GstTracer *dcu_tracer_new(const char *params);
void dcu_tracer_finish(GstTracer *tracer);

/* The in-process tracer: made once; `pre` registers its push/chain-pre hooks too. */
void dcu_in_process_tracer(gboolean pre);
/* Trace pad at (stage, point) into ring from the in-process tracer's hooks; returns a handle
 * (non-zero) or 0. dcu_hook_detach stops it. */
gulong dcu_hook_attach(DcuRing *ring, GstPad *pad, int stage, int point, int clock_id);
void dcu_hook_detach(GstPad *pad);

#endif
