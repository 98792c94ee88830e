"""Tracepoints on every element, the trace model, and shipping events to relays.

Four sub-packages, bottom-up; each imports only those before it (``tests/test_layers.py``):

    trace     the event model and what reads it: events, trace files, frame    core
              tables, the delay model, statistics, exports. The contract the
              relay reads.
    clocks    the node's clocks: what disciplines CLOCK_REALTIME, PTP, the UDP  core
              clock exchange (its datagrams are the relay's too)
    capture   tracepoints in C and Python, the GStreamer tracer, the shipping   trace, core, plugins, pipeline
              thread that drains them into exporters
    ship      the wire and the node's side of the relay protocol: batches,     trace, clocks, core
              envelope, link, the relay exporter, shipping a trace file

:mod:`dcuscope.probes.instrument` composes them for ``dcuscope run``: a pipeline's tracepoints wired to
its trace file and relays. The relay imports ``trace``, ``clocks`` and ``ship`` only.
"""
