"""What a tracepoint and a push-post hook cost: native vs Python probes, side by side.

Runs the same pipeline in five modes, each run in a fresh process, in interleaved repetitions
(the order rotates every repetition, so drifting machine load hits every mode alike), and
reports medians:

- ``none``: no probes, and no dcuscope tracer object in the process;
- ``hooks``: the tracer exists (made by attaching probes to a throwaway pipeline, then
  detaching them), the measured pipeline has no probes: every push of every pad runs the
  push-post hook, whose pad-state lookup misses. The hooks cannot be switched off while the
  native probes are on (the tracer lives as long as the process), so this is how their own
  cost shows: ns per hook call = (time hooks - time none) / hook calls (``native.hook_calls``);
- ``tracing``: no probes, GStreamer's tracing switched on by a tracer of its own that hooks
  no data flow (``GST_TRACERS=factories``: element creation only). Once any tracer hook exists,
  every hook site of the core (pushes, chains, queries, buffer refs) looks up its hooks; so
  ``hooks`` against ``tracing`` is what our hook's body adds to that;
- ``native``: the native pad probes on every stage, and the hooks (hitting on traced pads);
  ``native`` against ``hooks`` is then what the pad probes alone add;
- ``python``: Python pad probes (PyGObject), no tracer.

Per mode: µs per tracepoint = (time with probes - time without) / (frames x tracepoints per
frame), from wall time and from the process's CPU time (steadier on a shared machine);
throughput lost in % = 1 - fps with probes / fps without.

Scenarios: ``identity20`` (videotestsrc -> framestamp -> 20 x identity -> fakesink, 16x16
frames: nearly free stages, so the probes' own cost shows) and ``video`` (640x480 frames
through real conversion and scaling stages: a pipeline that does some work per frame).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_probes.py [--frames N] [--reps 5] [--quick]

A figure it cannot produce (no hook call or tracepoint counted, a cost of zero to divide by)
is ``n/a (reason)`` (benchmarks/figures.py). Without the native probes, or when a run fails,
it says why in one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(REPO))

from benchmarks.figures import NA, CannotRun, Notes, fmt, last_line, maximum, median, minimum, ratio, run  # noqa: E402
from core.gst import Gst  # noqa: E402
from probes import native  # noqa: E402
from probes.events import EXIT  # noqa: E402
from probes.tracer import attach  # noqa: E402

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
MODES = ("none", "tracing", "hooks", "native", "python")


def register_framestamp() -> None:
    from plugins import framestamp

    name, rank, cls = framestamp.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)


def run_once(description: str, mode: str, frames: int) -> dict:
    """``{wall, cpu, points, hooks}`` of one run from PLAYING to EOS: seconds, tracepoints per
    frame, push-post hook calls during the run."""
    pipe = Gst.parse_launch(description.format(frames=frames))
    tracer = None
    if mode in ("native", "python"):
        tracer = attach(pipe, "bench", backend=mode, capacity=frames * 64)
    hooks = native.hook_calls()
    wall, cpu = time.perf_counter(), time.process_time()
    pipe.set_state(Gst.State.PLAYING)
    msg = pipe.get_bus().timed_pop_filtered(600 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    hooks = native.hook_calls() - hooks
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
    return {"wall": wall, "cpu": cpu, "points": points, "hooks": hooks}


def child(scenario: str, mode: str, frames: int) -> None:
    """One measured run in this (fresh) process; prints its figures as JSON."""
    register_framestamp()
    description = SCENARIOS[scenario]
    if mode == "hooks":
        # Make the tracer (its hooks stay for the life of the process), then trace nothing.
        throwaway = Gst.parse_launch(description.format(frames=1))
        attach(throwaway, "bench", backend="native").detach()
    run_once(description, "none" if mode in ("hooks", "tracing") else mode, 20)  # warm-up: plugins, first calls
    print(json.dumps(run_once(description, "none" if mode in ("hooks", "tracing") else mode, frames)))


def spawn(scenario: str, mode: str, frames: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    env.pop("GST_TRACERS", None)
    if mode == "tracing":
        env["GST_TRACERS"] = "factories"
    res = subprocess.run([sys.executable, __file__, "--child", scenario, mode, str(frames)],
                         capture_output=True, text=True, env=env, cwd=REPO)
    if res.returncode != 0:
        raise CannotRun(f"a {scenario}/{mode} run failed: {last_line(res.stderr or res.stdout)}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def per_unit(samples: dict, mode: str, base: str, units: float, key: str, what: str = "units") -> list:
    """µs per unit of (mode - base), paired by repetition: slow drifts of the machine's load
    cancel out; the spread shows what is left of the noise. NA when no unit was counted."""
    return [ratio(s[key] - b[key], units, f"no {what} counted") * 1e6 for s, b in zip(samples[mode], samples[base])]


def report(name: str, frames: int, samples: dict) -> None:
    med = {m: median(s["wall"] for s in runs) for m, runs in samples.items()}
    points = samples["native"][0]["points"]
    hooks = median(s["hooks"] for s in samples["hooks"])
    reps = len(samples["none"])
    no_time = "the run took no time"
    print(f"\n== {name}: {frames} frames, {points} tracepoints and {fmt(ratio(hooks, frames), '.0f')} push-post hook "
          f"calls per frame, {reps} interleaved repetitions (a fresh process each), medians")
    print(f"no-probe time per frame: {fmt(med['none'] / frames * 1e6, '.1f')} µs")
    print(f"{'mode':7} {'fps':>8} {'x none':>7} {'lost %':>7} {'cost per unit, wall [min..max]':>34} {'CPU':>8}")
    print(f"{'none':7} {fmt(ratio(frames, med['none'], no_time), '8.0f')} {1:7.3f}")
    units = {"tracing": ("ns/hook", hooks, 1000, "push-post hook calls"),
             "hooks": ("ns/hook", hooks, 1000, "push-post hook calls"),
             "native": ("µs/tracepoint", frames * points, 1, "tracepoints"),
             "python": ("µs/tracepoint", frames * points, 1, "tracepoints")}
    notes = Notes()  # the n/a cells' reasons, under the table
    for m, (label, n, scale, what) in units.items():
        wall = [v * scale for v in per_unit(samples, m, "none", n, "wall", what)]
        cpu = median(per_unit(samples, m, "none", n, "cpu", what)) * scale
        spread = f"{label} {notes.cell(median(wall), '.2f')}"
        if not isinstance(median(wall), NA):
            spread += f" [{minimum(wall):.2f}..{maximum(wall):.2f}]"
        fps, x_none = ratio(frames, med[m], no_time), ratio(med["none"], med[m], no_time)
        print(f"{m:7} {notes.cell(fps, '.0f'):>8} {notes.cell(x_none, '.3f'):>7} "
              f"{notes.cell((1 - x_none) * 100, '.2f'):>7} {spread:>34} {notes.cell(cpu, '.2f'):>8}")
    for line in notes.lines():
        print(line)
    body = per_unit(samples, "hooks", "tracing", hooks, "wall", "push-post hook calls")
    body_cpu = median(per_unit(samples, "hooks", "tracing", hooks, "cpu", "push-post hook calls"))
    print(f"our hook's body (hooks - tracing): {fmt(median(body) * 1000, '.1f')} ns/hook wall, "
          f"{fmt(body_cpu * 1000, '.1f')} CPU; "
          f"fps hooks / tracing {fmt(ratio(med['tracing'], med['hooks'], no_time), '.3f')}")
    pads = per_unit(samples, "native", "hooks", frames * points, "wall", "tracepoints")
    pads_cpu = median(per_unit(samples, "native", "hooks", frames * points, "cpu", "tracepoints"))
    print(f"pad probes alone (native - hooks): {fmt(median(pads), '.3f')} µs/tracepoint wall, {fmt(pads_cpu, '.3f')} "
          f"CPU; fps native / hooks {fmt(ratio(med['hooks'], med['native'], no_time), '.3f')}")
    native_us = median(per_unit(samples, "native", "none", frames * points, "cpu", "tracepoints"))
    python_us = median(per_unit(samples, "python", "none", frames * points, "cpu", "tracepoints"))
    if not isinstance(native_us, (int, float)) or native_us > 0:
        times = ratio(python_us, native_us)
    else:  # the native probes cost nothing measurable next to the noise: no ratio to give
        times = ratio(python_us, 0, f"the native probes' CPU cost per tracepoint was {native_us:.3f} µs, not above 0")
    print(f"python / native cost per tracepoint: {fmt(times, '.0f', 'x')} (CPU)")


def bench(name: str, frames: int, reps: int) -> None:
    samples = {m: [] for m in MODES}
    for rep in range(reps):
        for mode in MODES[rep % len(MODES):] + MODES[: rep % len(MODES)]:
            samples[mode].append(spawn(name, mode, frames))
    report(name, frames, samples)


def main() -> int:
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, help=f"frames per run (default: {FRAMES})")
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--scenario", choices=[*SCENARIOS, "all"], default="all")
    parser.add_argument("--quick", action="store_true", help="a smoke test: identity20, 300 frames, 1 repetition")
    args = parser.parse_args()
    if args.quick:
        args.frames, args.reps, args.scenario = 300, 1, "identity20"
    if args.reps < 1 or (args.frames is not None and args.frames < 1):
        parser.error("--reps and --frames must be at least 1")
    if native.load() is None:
        raise CannotRun(f"the native probes are unavailable: {native.unavailable_reason()}")
    for name in SCENARIOS if args.scenario == "all" else [args.scenario]:
        bench(name, args.frames or FRAMES[name], args.reps)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
