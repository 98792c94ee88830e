"""Relay benchmark: sustained ingest (storage + live statistics) and UI-visible lag.

For each node count (default 2, 8, 32), on 127.0.0.1:

1. throughput: one relay process, N simulated node processes (``python -m probes.simnode``)
   each shipping its share of ``--events`` as fast as the relay acknowledges; the rate is
   events committed to SQLite per second between 10 % and 90 % of the total (every one of
   them also went through the live pairing);
2. lag: N nodes paced at ``--rate`` events/s each (the paper's DCU: ~4,300), a browser-side
   Socket.IO client on ``/ui``; lag = arrival of a ``frames`` push - the timestamp of the
   frame's last event (its sink enter). The node stamps an event when it happens and ships
   it within its flush interval (50 ms), so this includes the node's batching;
   ``push_transit`` is the part from the relay sending a push to the client handling it.

The relay and the node processes share this machine's cores: on a 2-core machine the nodes
take CPU from the relay, so the figures are a floor. Each phase also reports the relay's CPU
(% of one core: ``relay_cpu_pct``; in the throughput phase also within the 10-90 % window)
and that of all node processes (``nodes_cpu_pct``), and ``load_before`` (1-min load average
when it started: other work on the machine). Prints one JSON line per node count; a figure
a run could not produce is ``"n/a (reason)"`` there (benchmarks/figures.py).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_relay.py [--nodes 2 8 32] [--events 2000000]
        [--batch-events 8192] [--rate 4300] [--seconds 12] [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import socketio

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, dumps, last_line, percentile, run  # noqa: E402

SOURCES = 2
EVENTS_PER_FRAME = 12  # origin, 5 stages x enter/exit, sink enter
# Every simulated node connects from 127.0.0.1, where real DCUs each have their own address:
# the per-address cap (16 by default) would refuse the 17th node and the benchmark's own requests.
LOOPBACK = ("--limit", "connections_per_peer=256")


def _env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


class Relay:
    def __init__(self, db: Path, args: Sequence[str] = ()) -> None:
        """``args``: more ``python -m relay`` options (bench_exporters: --otlp, --frame-limit).
        Raises CannotRun, with the relay's last line of error, when it does not start."""
        self._errors = tempfile.TemporaryFile()  # not a pipe: nobody reads it while the relay runs
        self.proc = subprocess.Popen([sys.executable, "-m", "relay", "--port", "0", "--db", str(db), *LOOPBACK, *args],
                                     cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=self._errors)
        line = self.proc.stdout.readline().decode()
        m = re.search(r"http://127\.0\.0\.1:(\d+)", line)
        if not m:
            self.proc.kill()
            self.proc.wait(15)
            self._errors.seek(0)
            raise CannotRun(f"the relay did not start: {last_line(self._errors.read())}")
        self.url = f"http://127.0.0.1:{m.group(1)}"

    def get(self, path: str):
        with urllib.request.urlopen(self.url + path, timeout=30) as r:
            return json.loads(r.read())

    def cpu_s(self) -> float:
        """CPU seconds the relay process used so far (user + system)."""
        return _proc_cpu(self.proc.pid)

    def stored(self) -> int:
        return sum(run["events"] for s in self.get("/api/sessions") for run in s["runs"])

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)
        self._errors.close()


def start_nodes(url: str, n: int, per_node_events: int, paced: bool, fps: float,
                batch_events: int = 8192) -> list[subprocess.Popen]:
    frames = max(1, per_node_events // (EVENTS_PER_FRAME * SOURCES))
    procs = []
    for k in range(n):
        cmd = [sys.executable, "-m", "probes.simnode", "--relay", url, "--node", f"DCU-{k + 1}",
               "--sources", str(SOURCES), "--frames", str(frames), "--fps", str(fps), "--seed", str(k),
               "--close-timeout", "120", "--batch-events", str(batch_events)]
        if paced:
            cmd.append("--paced")
        procs.append(subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE))
    return procs


def wait_nodes(procs: list[subprocess.Popen], timeout: float) -> list[dict]:
    """Each node's counters (its last line of output); CannotRun with its error if one failed."""
    out = []
    for k, p in enumerate(procs):
        try:
            stdout, stderr = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            raise CannotRun(f"simulated node DCU-{k + 1} did not finish within {timeout:g} s") from None
        if p.returncode != 0 or not stdout.strip():
            raise CannotRun(f"simulated node DCU-{k + 1} failed (exit status {p.returncode}): {last_line(stderr)}")
        out.append(json.loads(stdout.decode().strip().splitlines()[-1]))
    return out


def throughput(n: int, total: int, tmp: Path, batch_events: int) -> dict:
    relay = Relay(tmp / f"tp{n}.db")
    try:
        return measure_throughput(relay, n, total, batch_events)
    finally:
        relay.stop()


def measure_throughput(relay: Relay, n: int, total: int, batch_events: int) -> dict:
    """The throughput phase on ``relay``, a fresh one: every event it stores is counted."""
    per_node = total // n
    expected = n * (per_node // (EVENTS_PER_FRAME * SOURCES)) * EVENTS_PER_FRAME * SOURCES
    children = _children_cpu()
    cpu0, wall0 = relay.cpu_s(), time.monotonic()
    procs = start_nodes(relay.url, n, per_node, paced=False, fps=1000.0, batch_events=batch_events)
    samples = []
    deadline = time.monotonic() + 600
    ended = None  # when every node had exited: the relay gets 2 s more to store what they sent, not 600
    while time.monotonic() < deadline:
        samples.append((time.monotonic(), relay.stored(), relay.cpu_s()))
        if samples[-1][1] >= expected or (ended is not None and time.monotonic() - ended > 2.0):
            break
        if ended is None and all(p.poll() is not None for p in procs):
            ended = time.monotonic()
        time.sleep(0.1)
    relay_cpu = relay.cpu_s() - cpu0
    wall = time.monotonic() - wall0
    counters = wait_nodes(procs, 120)
    t = np.array([s[0] for s in samples])
    v = np.array([s[1] for s in samples], float)
    c = np.array([s[2] for s in samples])
    lo, hi = np.searchsorted(v, 0.1 * expected), min(np.searchsorted(v, 0.9 * expected), len(v) - 1)
    if v[-1] < 0.9 * expected:
        why = NA(f"the relay stored {int(v[-1])} of {expected} events")
    elif hi > lo and t[hi] > t[lo]:
        why = None
    else:  # the run was shorter than two of the 0.1 s samples inside 10-90 %
        why = NA("no two samples of the stored count inside 10-90 % of the events: the run was too short")
    if why is None:
        span = float(t[hi] - t[lo])
        rate, window_s, window_cpu = round((v[hi] - v[lo]) / span), round(span, 2), round(100 * (c[hi] - c[lo]) / span)
    else:
        rate = window_s = window_cpu = why
    return {"batch_events": batch_events, "events": int(v[-1]), "events_per_s": rate,
            "lost": sum(c["lost"] for c in counters), "window_s": window_s, "relay_cpu_pct_in_window": window_cpu,
            "relay_cpu_pct": round(100 * relay_cpu / wall),
            "nodes_cpu_pct": round(100 * (_children_cpu() - children) / wall)}


async def _watch_ui(url: str, seconds: float) -> tuple[list[float], list[float]]:
    """Lags of the frames pushed (ms), and of the pushes themselves (arrival - relay send)."""
    lags: list[float] = []
    transit: list[float] = []
    sio = socketio.AsyncClient(reconnection=False)

    def on_frames(data: dict) -> None:
        now = time.clock_gettime_ns(time.CLOCK_REALTIME)
        transit.append((now - data["t_ns"]) / 1e6)
        for block in data["nodes"].values():
            corr = block["correction_ns"]
            for f in block["frames"]:
                last = max(t for t in f["enter"] + f["exit"] if t is not None) + corr
                lags.append((now - last) / 1e6)

    sio.on("frames", on_frames, namespace="/ui")
    try:
        await sio.connect(url, namespaces=["/ui"], transports=["websocket"], wait_timeout=10)
    except socketio.exceptions.ConnectionError as exc:
        raise CannotRun(f"the /ui client could not connect to the relay: {exc}") from exc
    await asyncio.sleep(seconds)
    await sio.disconnect()
    return lags, transit


def lag(n: int, rate: float, seconds: float, tmp: Path) -> dict:
    relay = Relay(tmp / f"lag{n}.db")
    try:
        return measure_lag(relay, n, rate, seconds)
    finally:
        relay.stop()


def measure_lag(relay: Relay, n: int, rate: float, seconds: float,
                on_window: Callable[[str], None] | None = None) -> dict:
    """The lag phase on ``relay``; ``on_window("start")`` / ``("end")`` are called as the
    measured window opens and closes (bench_exporters samples the exporters' counters there)."""
    fps = rate / (EVENTS_PER_FRAME * SOURCES)
    # Nodes run long enough to outlast their own start-up (Python imports: ~0.5 CPU-s
    # each, which on 2 cores and 32 nodes is seconds); measured only once all stream.
    procs = start_nodes(relay.url, n, int(rate * (seconds + 60)), paced=True, fps=fps)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        nodes = relay.get("/api/nodes")
        if len(nodes) == n and all(node["events"] > 0 for node in nodes):
            break
        time.sleep(0.5)
    time.sleep(1.0)
    if on_window:
        on_window("start")
    cpu0, wall0 = relay.cpu_s(), time.monotonic()
    nodes_cpu0 = sum(_proc_cpu(p.pid) for p in procs)
    lags, transit = asyncio.run(_watch_ui(relay.url, seconds))
    relay_cpu, wall = relay.cpu_s() - cpu0, time.monotonic() - wall0
    if on_window:
        on_window("end")
    nodes_cpu = sum(_proc_cpu(p.pid) for p in procs) - nodes_cpu0
    received = sum(node["events"] for node in relay.get("/api/nodes"))
    for p in procs:
        p.terminate()
    for p in procs:
        p.wait(30)
    no_frame = f"no frame reached the /ui client in the {seconds:g} s window"
    no_push = f"no push reached the /ui client in the {seconds:g} s window"
    return {"rate_per_node": rate, "seconds": seconds, "frames_seen": len(lags), "events_received": received,
            "lag_p50_ms": round(percentile(lags, 50, no_frame), 1),
            "lag_p99_ms": round(percentile(lags, 99, no_frame), 1),
            "push_transit_p50_ms": round(percentile(transit, 50, no_push), 1),
            "push_transit_p99_ms": round(percentile(transit, 99, no_push), 1),
            "relay_cpu_pct": round(100 * relay_cpu / wall), "nodes_cpu_pct": round(100 * nodes_cpu / wall)}


def _proc_cpu(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except FileNotFoundError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nodes", type=int, nargs="+", default=[2, 8, 32])
    p.add_argument("--events", type=int, default=2_000_000, help="events in all for the throughput phase")
    p.add_argument("--batch-events", type=int, default=8192,
                   help="events per batch in the throughput phase (a paced DCU at 4,300/s sends ~215)")
    p.add_argument("--rate", type=float, default=4300.0, help="events/s per node in the lag phase")
    p.add_argument("--seconds", type=float, default=12.0, help="length of the lag phase")
    p.add_argument("--quick", action="store_true", help="a smoke test: 2 nodes, 600,000 events, a 1.5 s lag phase")
    args = p.parse_args(argv)
    if args.quick:
        args.nodes, args.events, args.seconds = [2], 600_000, 1.5
    if min(args.nodes) < 1 or args.events < 1 or args.seconds <= 0 or args.rate <= 0:
        p.error("--nodes, --events, --seconds and --rate must be positive")
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.nodes:
            result = {"nodes": n, "cpus": os.cpu_count(), "load_before": round(os.getloadavg()[0], 1),
                      "throughput": throughput(n, args.events, Path(tmp), args.batch_events),
                      "lag": lag(n, args.rate, args.seconds, Path(tmp))}
            print(dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
