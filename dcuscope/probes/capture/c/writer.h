/* The trace writer (writer.c): a thread that drains a ring into a trace file, for the GStreamer
 * tracer. Above ring.h and graph.h. */
#ifndef DCU_WRITER_H
#define DCU_WRITER_H

#include "graph.h"
#include "ring.h"

typedef struct DcuWriter DcuWriter;

/* Start the thread that drains ring into the trace file at path (format 2, probes/trace/tracefile.py).
 * Returns NULL and prints why when the file cannot be written. */
DcuWriter *dcu_writer_start(DcuRing *ring, DcuGraph *graph, const char *path, const char *node,
                            const char *clock_name, int64_t started_ns);
/* Drain what is left, write the end line, close the file and free the writer (idempotent per writer). */
void dcu_writer_stop(DcuWriter *writer);

#endif
