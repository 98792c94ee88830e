/* The graph of stages and sources the dcuscope tracer discovers (tracer.c fills it) and its trace
 * writer reads (writer.c), and walking a link downstream (graph.c). Above ring.h. */
#ifndef DCU_GRAPH_H
#define DCU_GRAPH_H

#include "ring.h"

#define MAX_SOURCES 1024
#define LINEAGE_LOST_AFTER 4 /* buffers without identity a stage pushed, none with, after frames entered */

/* A stage: one non-bin element that frames with an identity passed. */
typedef struct {
  int index;       /* internal index: the ring's stage number */
  GWeakRef element;
  char *name;      /* unique among the stages */
  char *factory;
  gboolean aggregator;
  gboolean source_element; /* no sink pads: frames start here */
  _Atomic int entered;      /* identified frames have entered it */
  _Atomic int pushed_identified; /* it pushed buffers with identity */
  _Atomic uint64_t unidentified_out; /* buffers without identity it pushed after frames entered */
  _Atomic uint64_t shared;  /* frames it could not give an identity: their buffers were shared */
  _Atomic int keep_history; /* it posted QoS: remember recent inputs, to name the frames it drops */
  _Atomic uint64_t qos_unnamed; /* QoS drops whose frames were not (yet) remembered */
} DcuStage;

/* What the writer needs to know of the tracer's discoveries. Guarded by lock; version grows
 * with every change the trace header must show. */
typedef struct {
  GMutex lock;
  DcuStage *stages[MAX_STAGES];
  int n_stages;
  char *sources[MAX_SOURCES]; /* source id -> description */
  int n_sources;
  _Atomic int version;
  GQuark stage_quark; /* element qdata -> its DcuStage */
  guint8 *edges;      /* [a * MAX_STAGES + b]: stage a pushed buffers to stage b */
} DcuGraph;

/* The element downstream of a src pad, through ghost and proxy pads (a reference), or NULL. */
GstElement *dcu_downstream_element(GstPad *src);

#endif
