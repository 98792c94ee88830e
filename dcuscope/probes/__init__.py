"""Tracepoints on every element, trace files, and shipping events to relays.

Four sub-packages, bottom-up; each imports only those before it (``tests/test_layers.py``):

    trace     trace files and what reads them: stats, exports (the events are   core, protocol, model
              dcuscope.protocol's, their delays dcuscope.model's)
    clocks    the node's clocks: what disciplines CLOCK_REALTIME, PTP, the      core, protocol
              node's side of the UDP clock exchange
    capture   tracepoints in C and Python, the GStreamer tracer, the shipping   trace, core, plugins, pipeline
              thread that drains them into exporters
    ship      the node's side of the relay protocol: link, outbox, failover,   trace, clocks, core, protocol
              spool, the relay exporter, shipping a trace file

:mod:`dcuscope.probes.instrument` composes them for ``dcuscope run``: a pipeline's tracepoints wired to
its trace file and relays. The relay imports nothing of probes: what both sides speak is
:mod:`dcuscope.protocol`, what the events mean :mod:`dcuscope.model`.
"""
