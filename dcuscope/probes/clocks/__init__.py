"""The node's clocks: what disciplines the CLOCK_REALTIME the probes read (:mod:`.sysclock`), the
PTP state from linuxptp (:mod:`.ptp`), and the node's side of the UDP clock exchange with the relay
(:mod:`.udpclock`; its datagrams: :mod:`dcuscope.protocol.clockdatagram`).

Imports nothing of probes (``core`` and ``protocol`` only).
"""
