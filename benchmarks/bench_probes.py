"""What a tracepoint costs, all included: dcuscope's tracer (hooks, in process and through
GST_TRACERS), its pad probes, GStreamer's own latency tracer and Python probes, side by side.

Runs the same pipeline in six modes, each run in a fresh process, in interleaved repetitions
(the order rotates every repetition, so drifting machine load hits every mode alike), and
reports medians:

- ``none``: no tracer, no probes;
- ``latency``: GStreamer's ``latency`` tracer (``GST_TRACERS=latency(flags=element)``, its log
  off), the anchor users know: per-element times on the same pushes;
- ``probes``: dcuscope's native tracepoints fired by pad probes (plus the tracer's push-post
  hook, which service/wait needs);
- ``hooks``: the same tracepoints fired by the dcuscope tracer's own hooks, in process (the
  default of ``dcuscope run --probes``);
- ``tracer``: ``GST_TRACERS=dcuscope`` as any application loads it: every element traced from
  hooks alone, frames given their identity by the tracer, its C thread writing the trace file;
- ``python``: Python pad probes (PyGObject).

Per mode: µs per tracepoint = (time with it - time without) / tracepoint hits, from wall time
and from the process's CPU time (steadier on a shared machine), everything included (GStreamer's
hook dispatch, our hooks or probes, the ring, the draining thread). A tracepoint is one buffer
at one traced pad: a frame crossing a link is two (exit, enter). For ``latency``, which keeps
no records, the hits are those of ``hooks`` on the same pipeline. Throughput lost in % = 1 -
fps with / fps without.

Scenarios: ``identity20`` (videotestsrc -> framestamp -> 20 x identity -> fakesink, 16x16
frames: nearly free stages, so the tracepoints' own cost shows) and ``video`` (640x480 frames
through real conversion and scaling stages: a pipeline that does some work per frame). Under
``tracer`` the framestamp (a Python element every mode runs) is one more traced stage, and the
tracer gives frames their identity at the source itself.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_probes.py [--frames N] [--reps 5] [--quick]
        [--against DIR]

``--against DIR`` measures another checkout of dcuscope beside this one (``git worktree add DIR
REV``), or a venv where dcuscope is installed (``pip install``: its Python, its site-packages'
dcuscope and the native library its install built), every mode run in both trees in turn, each
tree's children from its own code and native library; it prints both tables (each with the
dcuscope it imported) and the CPU cost per tracepoint of this tree over that one.

A figure it cannot produce (no tracepoint counted, a cost of zero to divide by) is ``n/a
(reason)`` (benchmarks/figures.py). Without the native probes, or when a run fails, it says
why in one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
INSTALLED_ENV = "DCUSCOPE_BENCH_INSTALLED"
"""Set in a child measuring an installed dcuscope: ``benchmarks`` comes from this checkout, dcuscope
from the venv's site-packages (the checkout goes last on sys.path)."""
if str(REPO) not in sys.path:  # run as a script: make the project importable
    if os.environ.get(INSTALLED_ENV):
        sys.path.append(str(REPO))
    else:
        sys.path.insert(0, str(REPO))

from benchmarks.figures import NA, CannotRun, Notes, fmt, last_line, maximum, median, minimum, ratio, run  # noqa: E402
from dcuscope.core.gst import Gst  # noqa: E402
from dcuscope.probes.capture import native  # noqa: E402
from dcuscope.probes.capture.tracer import attach  # noqa: E402
from dcuscope.protocol.events import EXIT  # noqa: E402

SCENARIOS = {
    "identity20": "videotestsrc num-buffers={frames} ! video/x-raw,width=16,height=16,format=RGB ! framestamp ! "
                  + " ! ".join(f"identity name=i{i}" for i in range(20)) + " ! fakesink sync=false",
    "video": "videotestsrc num-buffers={frames} ! video/x-raw,width=640,height=480,format=I420 ! framestamp ! "
             "videoconvert name=convert ! video/x-raw,format=RGB ! videoscale name=scale ! "
             "video/x-raw,width=320,height=240 ! queue name=queue ! videoflip name=flip method=horizontal-flip ! "
             "fakesink name=sink sync=false",
}
FRAMES = {"identity20": 10000, "video": 2000}
"""Default frames per run: enough for a run of the near-free chain to last about half a second."""
MODES = ("none", "latency", "probes", "hooks", "tracer", "python")
ATTACHED = {"probes": ("native", "probes"), "hooks": ("native", "hooks"), "python": ("python", "probes")}
"""Modes whose tracepoints probes.capture.tracer places: (backend, trigger)."""


def register_framestamp() -> None:
    from dcuscope.plugins import framestamp

    name, rank, cls = framestamp.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)


def run_once(description: str, mode: str, frames: int) -> dict:
    """``{wall, cpu, points}`` of one run from PLAYING to EOS: seconds, and the tracepoints per
    frame that probes.capture.tracer placed (0 in the other modes)."""
    pipe = Gst.parse_launch(description.format(frames=frames))
    tracer = None
    if mode in ATTACHED:
        backend, trigger = ATTACHED[mode]
        tracer = attach(pipe, "bench", backend=backend, trigger=trigger, capacity=frames * 64)
    wall, cpu = time.perf_counter(), time.process_time()
    pipe.set_state(Gst.State.PLAYING)
    msg = pipe.get_bus().timed_pop_filtered(600 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    pipe.set_state(Gst.State.NULL)
    if msg is None or msg.type != Gst.MessageType.EOS:
        raise SystemExit(f"{mode}: pipeline failed: {msg.parse_error() if msg else 'timeout'}")
    points = 0
    if tracer is not None:
        points = tracer.tracepoints
        events, stats = tracer.drain(), tracer.stats()
        tracer.detach()
        # Every tracepoint must have fired once per frame, or the cost per tracepoint is wrong
        # (native probes also write ready points and thread facts: not tracepoint hits).
        hits = int((events["point"] <= EXIT).sum())
        if hits != frames * points or stats.dropped or stats.unidentified:
            raise SystemExit(f"{mode}: {hits} events for {frames} frames x {points} tracepoints, "
                             f"{stats.dropped} dropped, {stats.unidentified} unidentified")
    import dcuscope

    return {"wall": wall, "cpu": cpu, "points": points, "code": str(Path(dcuscope.__file__).parent)}


def child(scenario: str, mode: str, frames: int, trace: str | None = None) -> None:
    """One measured run in this (fresh) process; prints its figures as JSON."""
    register_framestamp()
    description = SCENARIOS[scenario]
    run_once(description, mode, 20)  # warm-up: plugins, first calls
    result = run_once(description, mode, frames)
    if trace:  # the GST_TRACERS tracer: its trace is complete once GStreamer is deinitialised
        Gst.deinit()
        from dcuscope.probes.trace.tracefile import read_trace

        t = read_trace(trace)
        hits = int((t.events["point"] <= EXIT).sum())
        if t.dropped or hits % (frames + 20):
            raise SystemExit(f"tracer: {hits} events for {frames + 20} frames, {t.dropped} dropped")
        result["points"] = hits // (frames + 20)
    print(json.dumps(result))


_PLUGIN_PATHS: dict[Path, str] = {}


def installed(tree: Path) -> bool:
    """Whether ``tree`` is a venv with dcuscope installed (else a checkout)."""
    return (tree / "bin" / "dcuscope").exists() and not (tree / "benchmarks" / "bench_probes.py").exists()


def tree_env(tree: Path) -> dict:
    """The environment a child of ``tree`` runs in: its code first on the path."""
    if installed(tree):
        return {**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, INSTALLED_ENV: "1"}
    return {**os.environ, "PYTHONPATH": str(tree) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def plugin_path(tree: Path) -> str:
    """The folder of ``tree``'s GStreamer plugin, built by that tree's own code (installed: the one
    its install built)."""
    if tree not in _PLUGIN_PATHS:
        cmd = [str(tree / "bin" / "dcuscope")] if installed(tree) else [sys.executable, "-m", "dcuscope.cli"]
        res = subprocess.run([*cmd, "plugin-path"], capture_output=True, text=True, env=tree_env(tree),
                             cwd=tempfile.gettempdir() if installed(tree) else tree)
        if res.returncode != 0:
            raise CannotRun(f"cannot build the plugin of {tree}: {last_line(res.stderr or res.stdout)}")
        _PLUGIN_PATHS[tree] = res.stdout.strip().splitlines()[-1]
    return _PLUGIN_PATHS[tree]


def spawn(scenario: str, mode: str, frames: int, tree: Path = REPO) -> dict:
    """One run in a fresh process, from ``tree``'s code (this checkout, or ``--against``'s)."""
    env = tree_env(tree)
    env.pop("GST_TRACERS", None)
    with tempfile.TemporaryDirectory() as tmp:
        args = [scenario, mode, str(frames)]
        if mode == "latency":
            env["GST_TRACERS"] = "latency(flags=element)"
        elif mode == "tracer":
            trace = str(Path(tmp) / "bench.trace.jsonl")
            env["GST_PLUGIN_PATH"] = plugin_path(tree)
            # A ring as large as the other modes' (they drain once, at the end): no drops.
            env["GST_TRACERS"] = f"dcuscope(node=bench,trace={trace},capacity={(frames + 20) * 128})"
            args.append(trace)
        python, script = (tree / "bin" / "python", REPO) if installed(tree) else (sys.executable, tree)
        res = subprocess.run([str(python), str(script / "benchmarks" / "bench_probes.py"), "--child", *args],
                             capture_output=True, text=True, env=env, cwd=tmp)
    if res.returncode != 0:
        raise CannotRun(f"a {scenario}/{mode} run of {tree} failed: {last_line(res.stderr or res.stdout)}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def per_unit(samples: dict, mode: str, base: str, units: float, key: str, what: str = "units") -> list:
    """µs per unit of (mode - base), paired by repetition: slow drifts of the machine's load
    cancel out; the spread shows what is left of the noise. NA when no unit was counted."""
    return [ratio(s[key] - b[key], units, f"no {what} counted") * 1e6 for s, b in zip(samples[mode], samples[base])]


def report(name: str, frames: int, samples: dict) -> dict:
    """Print the table; returns each mode's median CPU µs per tracepoint."""
    med = {m: median(s["wall"] for s in runs) for m, runs in samples.items()}
    points = {m: samples[m][0]["points"] for m in samples}
    points["latency"] = points["hooks"]  # the same pushes; it keeps no records to count
    reps = len(samples["none"])
    no_time = "the run took no time"
    print(f"\n== {name}: {frames} frames, {points['hooks']} tracepoints per frame ({points['tracer']} under "
          f"GST_TRACERS=dcuscope), {reps} interleaved repetitions (a fresh process each), medians")
    print(f"no-tracer time per frame: {fmt(med['none'] / frames * 1e6, '.1f')} µs")
    print(f"{'mode':7} {'fps':>8} {'x none':>7} {'lost %':>7} {'µs per tracepoint, wall [min..max]':>36} {'CPU':>8}")
    print(f"{'none':7} {fmt(ratio(frames, med['none'], no_time), '8.0f')} {1:7.3f}")
    notes = Notes()  # the n/a cells' reasons, under the table
    cpu_cost = {}
    for m in MODES[1:]:
        n = frames * points[m]
        wall = per_unit(samples, m, "none", n, "wall", "tracepoints")
        cpu_cost[m] = median(per_unit(samples, m, "none", n, "cpu", "tracepoints"))
        spread = notes.cell(median(wall), '.3f')
        if not isinstance(median(wall), NA):
            spread += f" [{minimum(wall):.3f}..{maximum(wall):.3f}]"
        fps, x_none = ratio(frames, med[m], no_time), ratio(med["none"], med[m], no_time)
        print(f"{m:7} {notes.cell(fps, '.0f'):>8} {notes.cell(x_none, '.3f'):>7} "
              f"{notes.cell((1 - x_none) * 100, '.2f'):>7} {spread:>36} {notes.cell(cpu_cost[m], '.3f'):>8}")
    for line in notes.lines():
        print(line)
    for a, b in (("hooks", "probes"), ("hooks", "latency"), ("python", "hooks")):
        x, y = cpu_cost[a], cpu_cost[b]
        why = f"the {b} cost per tracepoint was {y:.3f} µs, not above 0" if isinstance(y, (int, float)) and y <= 0 else None
        print(f"{a} / {b} cost per tracepoint: {fmt(ratio(x, y if why is None else 0, why), '.2f', 'x')} (CPU)")
    return cpu_cost


def bench(name: str, frames: int, reps: int, against: Path | None = None) -> None:
    trees = [REPO] + ([against] if against else [])
    samples = {tree: {m: [] for m in MODES} for tree in trees}
    for rep in range(reps):
        for mode in MODES[rep % len(MODES):] + MODES[: rep % len(MODES)]:
            for tree in trees if rep % 2 == 0 else trees[::-1]:
                samples[tree][mode].append(spawn(name, mode, frames, tree))
    if against is None:
        report(name, frames, samples[REPO])
        return
    costs = {}
    for tree in trees:
        print(f"\n-- tree {tree} (its dcuscope: {samples[tree]['none'][0]['code']})")
        costs[tree] = report(name, frames, samples[tree])
    print(f"\n{name}: µs per tracepoint (CPU), this tree / {against}:")
    for m in MODES[1:]:
        this, that = costs[REPO][m], costs[against][m]
        why = None if isinstance(that, (int, float)) and that > 0 else "no cost to divide by"
        print(f"  {m:7} {fmt(this, '.3f')} / {fmt(that, '.3f')} = {fmt(ratio(this, that if why is None else 0, why), '.2f', 'x')}")


def main() -> int:
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]), *sys.argv[5:])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, help=f"frames per run (default: {FRAMES})")
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--scenario", choices=[*SCENARIOS, "all"], default="all")
    parser.add_argument("--quick", action="store_true", help="a smoke test: identity20, 300 frames, 1 repetition")
    parser.add_argument("--against", type=Path, metavar="DIR",
                        help="another checkout of dcuscope (e.g. git worktree add DIR HEAD~1), or a venv where "
                             "dcuscope is installed (pip install), measured beside this one")
    args = parser.parse_args()
    if args.quick:
        args.frames, args.reps, args.scenario = 300, 1, "identity20"
    if args.reps < 1 or (args.frames is not None and args.frames < 1):
        parser.error("--reps and --frames must be at least 1")
    against = args.against.resolve() if args.against else None
    if against is not None and not (against / "benchmarks" / "bench_probes.py").exists() and not installed(against):
        parser.error(f"--against {args.against}: neither a dcuscope checkout (no benchmarks/bench_probes.py) "
                     f"nor a venv with dcuscope installed (no bin/dcuscope)")
    if native.load() is None:
        raise CannotRun(f"the native probes are unavailable: {native.unavailable_reason()}")
    for name in SCENARIOS if args.scenario == "all" else [args.scenario]:
        bench(name, args.frames or FRAMES[name], args.reps, against)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
