"""The clocks probes can read, by name: Linux clock ids for ``time.clock_gettime_ns``.

``realtime`` is what PTP's phc2sys disciplines, so it is the default everywhere.
"""

CLOCKS = {"realtime": 0, "monotonic": 1, "tai": 11}
