"""The node's clocks: what disciplines the CLOCK_REALTIME the probes read (:mod:`.sysclock`), the
PTP state from linuxptp (:mod:`.ptp`), and the UDP clock exchange with the relay (:mod:`.udpclock`,
whose datagrams the relay also speaks).

Imports nothing of probes (``core`` only).
"""
