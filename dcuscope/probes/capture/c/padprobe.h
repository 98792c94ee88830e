/* Tracepoints fired by pad probes (padprobe.c), the other trigger beside the tracer's hooks
 * (probes/capture/native.py: trigger="probes"). Called from Python only. Above ring.h and tracer.h. */
#ifndef DCU_PADPROBE_H
#define DCU_PADPROBE_H

#include "ring.h"

/* Add a tracepoint on pad; returns the probe id (0 when pad is not a GstPad). The probe holds
 * a reference on the ring until it is removed. */
gulong dcu_attach(DcuRing *ring, GstPad *pad, int stage, int point, int clock_id);
void dcu_detach(GstPad *pad, gulong probe_id);

#endif
