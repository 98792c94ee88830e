"""stored == sent: NODE's one run in a relay's store holds exactly the events of TRACE, each once.

    python scripts/platforms/stored_vs_sent.py DB TRACE NODE

Prints ``N events stored == sent`` and exits 0, or says what differs and exits 1 (scripts/platforms.sh).
"""

from __future__ import annotations

import sys

import numpy as np

from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.relay.store.runs import list_sessions, load_runs

ORDER = ["source", "frame", "stage", "point", "ts"]


def main(db: str, trace: str, node: str) -> int:
    sent = read_trace(trace).events
    runs = [r for s in list_sessions(db) for r in s["runs"] if r["node"] == node]
    if len(runs) != 1:
        print(f"{len(runs)} runs of {node} stored, not one")
        return 1
    (stored,) = load_runs(db, runs[0]["run"], corrected=False)
    if len(stored.events) != len(sent) or not np.array_equal(np.sort(stored.events, order=ORDER),
                                                             np.sort(sent, order=ORDER)):
        print(f"{len(stored.events)} events stored, {len(sent)} sent: they differ")
        return 1
    print(f"{len(sent)} events stored == sent")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
