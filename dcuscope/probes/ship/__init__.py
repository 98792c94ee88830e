"""Shipping: the node's side of the relay protocol (the protocol itself: :mod:`dcuscope.protocol`).

- :mod:`.relaylink` (one WebSocket), :mod:`.outbox` (batches until acknowledged),
  :mod:`.failover` (which relay, when to move on), :mod:`.clockreport` (clock samples and
  reports), :mod:`.relayexport` (the exporter that composes them), :mod:`.spool` (batches on disk
  until a relay stores them).
- :mod:`.tailship` (a trace file being written, to a relay) and :mod:`.simnode` (a simulated node).

Imports :mod:`dcuscope.probes.trace` and :mod:`dcuscope.probes.clocks`; never :mod:`dcuscope.probes.capture`.
"""
