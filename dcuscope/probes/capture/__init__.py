"""Capture: tracepoints on a pipeline's pads without touching element code, and the thread that
drains them into exporters.

- ``c/``: the native library (ring, tracepoints, the dcuscope GStreamer tracer, its trace
  writer), built by :mod:`.native`; its C modules layer one way (:data:`.native.MODULES`; docs/development.md, "Layout").
- :mod:`.tracer` places tracepoints on a built pipeline (native, or :mod:`.ring`'s Python probes);
  :mod:`.processtracer` runs the GStreamer tracer for a whole process; :mod:`.sourcewatch` adds
  drops and source facts; :mod:`.shipper` drains the ring into exporters.

Imports :mod:`dcuscope.probes.trace` (the event record, trace files), ``core``, ``plugins``, ``pipeline``;
never :mod:`dcuscope.probes.ship` (exporters arrive through the ``Exporter`` protocol).
"""
