"""The trace model: the event record, trace files, frame tables, the delay model, statistics and
exports (Perfetto, CSV). What a node records and what the relay and ``dcuscope stats`` read of it.

Imports nothing of probes (``core`` only): capture writes it, ship carries it, the relay reads it.
"""
