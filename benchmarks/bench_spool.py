"""What the node's spool costs and how fast it drains (issue 63; docs/relay.md, "A DCU offline for a day").

1. Node CPU per event, spool off / on (synced every 200 ms, the default) / on synced every batch: the
   simulated node (``probes.ship.simnode``, every event shipped as fast as the relay takes it) against
   one SQLite relay, each run a fresh process, the three modes interleaved ``--reps`` times (the order
   rotating, so a drifting load hits each alike); the node's CPU (user + system, from the kernel's
   accounting of the child) per event, medians, and each mode's ratio to "off" (the goal: on within
   1.15x of off).
2. Disk bytes per spooled event: the same node with its relay down, its spool's bytes / its events.
3. Drain rate: that spool sent to a SQLite relay by ``dcuscope ship --drain`` (the rate it reports:
   events acknowledged, i.e. committed, per second from its connection; the goal: >= 1 M events/s).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_spool.py [--events N] [--reps 3] [--quick]
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.figures import CannotRun, fmt, ratio, run  # noqa: E402

MODES = {"off": ["--no-spool"], "on": [], "on, fsync every batch": ["--spool-fsync", "0"]}
SOURCES, EVENTS_PER_FRAME = 4, 12


def _python() -> list[str]:
    return [sys.executable]


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def start_relay(db: Path, port: int = 0) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([*_python(), "-m", "dcuscope.relay", "--port", str(port), "--db", str(db)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    line = proc.stdout.readline()
    m = re.search(r"http://\S+:(\d+)", line)
    if not m:
        proc.kill()
        raise CannotRun(f"the relay did not start: {line.strip()!r}")
    return proc, f"http://127.0.0.1:{m.group(1)}"


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()


def node(url: str, name: str, frames: int, spool: Path, extra: list[str], close_timeout: float = 60) -> dict:
    """One simulated node run; its counters and its CPU seconds."""
    cpu = _children_cpu()
    done = subprocess.run([*_python(), "-m", "dcuscope.probes.ship.simnode", "--relay", url, "--node", name,
                           "--frames", str(frames), "--sources", str(SOURCES), "--spool", str(spool),
                           "--close-timeout", str(close_timeout), *extra], cwd=REPO, capture_output=True, text=True,
                          timeout=600)
    if not done.stdout.strip():
        raise CannotRun(f"the simulated node failed: {done.stderr.strip()[-300:]}")
    return dict(json.loads(done.stdout.splitlines()[-1]), cpu_s=_children_cpu() - cpu)


def cpu_per_event(tmp: Path, frames: int, reps: int) -> dict[str, list[float]]:
    relay, url = start_relay(tmp / "cpu.db")
    got: dict[str, list[float]] = {m: [] for m in MODES}
    try:
        for rep in range(reps):
            order = list(MODES)[rep % len(MODES):] + list(MODES)[:rep % len(MODES)]
            for mode in order:
                c = node(url, f"N{rep}-{len(got[mode])}-{list(MODES).index(mode)}", frames, tmp / "spool-cpu",
                         MODES[mode])
                if c["acked"] != c["events"]:
                    raise CannotRun(f"mode {mode}: the relay stored {c['acked']} of {c['events']} events")
                got[mode].append(1e6 * c["cpu_s"] / c["events"])
                print(f"rep {rep + 1}: spool {mode:<22} {c['events']} events, node CPU {c['cpu_s']:.2f} s, "
                      f"{got[mode][-1]:.3f} µs/event", flush=True)
    finally:
        stop(relay)
    return got


def spool_and_drain(tmp: Path, frames: int, reps: int) -> tuple[list[float], list[float]]:
    per_event, rates = [], []
    for rep in range(reps):
        spool, db = tmp / f"spool-drain-{rep}", tmp / f"drain-{rep}.db"
        c = node("http://127.0.0.1:9", f"OFFLINE-{rep}", frames, spool, [], close_timeout=0.5)  # nothing listens
        size = sum(p.stat().st_size for p in spool.rglob("*.seg"))
        per_event.append(size / c["events"])
        relay, url = start_relay(db)
        try:
            done = subprocess.run([*_python(), "-m", "dcuscope.cli", "ship", "--drain", "--spool", str(spool),
                                   "--relay", url], cwd=REPO, capture_output=True, text=True, timeout=600)
        finally:
            stop(relay)
        m = re.search(r"all (\d+) events stored in [\d.]+ s \((\d+)/s\)", done.stdout)
        if done.returncode != 0 or not m or int(m.group(1)) != c["events"]:
            raise CannotRun(f"the drain failed: {(done.stdout + done.stderr).strip()[-300:]}")
        rates.append(float(m.group(2)))
        print(f"rep {rep + 1}: {c['events']} events spooled in {size} bytes ({per_event[-1]:.2f} B/event), "
              f"drained at {rates[-1] / 1e6:.2f} M events/s", flush=True)
    return per_event, rates


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--events", type=int, default=960_000, help="events per node run (default 960000)")
    p.add_argument("--drain-events", type=int, default=1_920_000, help="events spooled, then drained (default 1920000)")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="a smoke run: 48,000 events, one repetition")
    args = p.parse_args()
    if args.quick:
        args.events, args.drain_events, args.reps = 48_000, 48_000, 1
    frames = max(1, args.events // (SOURCES * EVENTS_PER_FRAME))
    with tempfile.TemporaryDirectory(prefix="bench-spool-") as tmp:
        cpu = cpu_per_event(Path(tmp), frames, args.reps)
        per_event, rates = spool_and_drain(Path(tmp), max(1, args.drain_events // (SOURCES * EVENTS_PER_FRAME)),
                                           args.reps)
    off = statistics.median(cpu["off"])
    print(f"\nnode CPU per event ({args.reps} interleaved reps of {frames * SOURCES * EVENTS_PER_FRAME} events, medians):")
    print(f"  {'spool':<24}{'µs/event':>10}{'vs off':>9}")
    for mode, values in cpu.items():
        med = statistics.median(values)
        print(f"  {mode:<24}{med:>10.3f}{fmt(ratio(med, off), '.2f', 'x'):>9}")
    print(f"disk: {statistics.median(per_event):.2f} bytes per spooled event (24 per event, 20 per batch record)")
    print(f"drain into SQLite: {statistics.median(rates) / 1e6:.2f} M events/s (median of {len(rates)})")
    print(json.dumps({"cpu_us_per_event": {m: statistics.median(v) for m, v in cpu.items()},
                      "on_vs_off": statistics.median(cpu["on"]) / off,
                      "fsync_every_batch_vs_off": statistics.median(cpu["on, fsync every batch"]) / off,
                      "bytes_per_event": statistics.median(per_event), "drain_events_per_s": statistics.median(rates)}))


if __name__ == "__main__":
    sys.exit(run(main, "bench_spool"))
