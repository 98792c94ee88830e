"""Helpers for the tests of live stops: a run timed line by line, and every frame accounted for."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dcuscope.model.delays import chains
from dcuscope.model.frametable import frame_table
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import DROP, ORIGIN
from tests.conftest import REPO, cli_env


@dataclass
class TimedRun:
    returncode: int
    stderr: str
    stop_said_at: float | None
    """time.monotonic() when the run said it was stopping (its deadline, as the run measured it)."""
    ended_at: float
    """time.monotonic() when the process had exited."""


def run_timed(*args, cwd: Path, stop_line: str = "stopping", timeout: float = 180) -> TimedRun:
    """``dcuscope ARGS`` as a user runs it, noting when its stderr says ``stop_line`` and when it exits."""
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", *map(str, args)], cwd=cwd, env=cli_env(),
                            stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(timeout, proc.kill)
    watchdog.start()
    lines, said = [], None
    try:
        for line in proc.stderr:
            lines.append(line)
            if said is None and stop_line in line:
                said = time.monotonic()
        proc.wait()
    finally:
        watchdog.cancel()
    return TimedRun(proc.returncode, "".join(lines), said, time.monotonic())


def check_every_frame_accounted(trace_path: Path) -> dict[str, int]:
    """Every frame stamped at a source (an origin event) either reached the sink (a complete
    chain) or was counted as dropped, never both; so says ``dcuscope stats`` too. Returns the
    frames dropped per reason."""
    trace = read_trace(trace_path)
    events = trace.events
    table = frame_table(trace.header, events)
    complete = chains(table).complete
    origins = events[events["point"] == ORIGIN]
    drops = events[events["point"] == DROP]
    stamped = set(zip(origins["source"].tolist(), origins["frame"].tolist()))
    reached = set(zip(table.source[complete].tolist(), table.frame[complete].tolist()))
    dropped = list(zip(drops["source"].tolist(), drops["frame"].tolist()))
    assert len(stamped) == len(origins), "a frame stamped twice"
    assert len(set(dropped)) == len(dropped), "a frame counted as dropped twice"
    assert not reached & set(dropped), "a frame both delivered and counted as dropped"
    assert reached | set(dropped) == stamped, (
        f"{len(stamped - reached - set(dropped))} frames stamped but neither delivered nor counted as dropped")

    stats = subprocess.run([sys.executable, "-m", "dcuscope.cli", "stats", str(trace_path), "--json"], env=cli_env(),
                           cwd=REPO, capture_output=True, text=True, timeout=120)
    assert stats.returncode == 0, stats.stderr
    (node,) = json.loads(stats.stdout)["nodes"].values()
    by_reason: dict[str, int] = {}
    for src in node["sources"].values():
        for reason, n in src["dropped"].items():
            by_reason[reason] = by_reason.get(reason, 0) + n
    delivered = sum(src["delivered"] for src in node["sources"].values())
    assert delivered == len(stamped) and node["frames"]["complete"] == len(reached)
    assert node["frames"]["incomplete"] == sum(by_reason.values()) == len(dropped), (node["frames"], by_reason)
    for source in np.unique(origins["source"]).tolist():  # and so, per source, as the stats list them
        src = node["sources"][str(source)]
        mine = sum(1 for s, _ in reached if s == source)
        assert src["delivered"] == mine + sum(src["dropped"].values()), (source, src, mine)
    return by_reason
