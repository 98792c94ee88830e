"""What a tracepoint costs: native vs Python probes, side by side.

Runs the same pipeline with no probes, with native probes and with Python probes, in
interleaved repetitions (the order rotates every repetition, so drifting machine load hits
every mode alike), and reports medians:

- µs per tracepoint = (time with probes - time without) / (frames x tracepoints per frame),
  from wall time and from the process's CPU time (steadier on a shared machine);
- throughput lost in % = 1 - fps with probes / fps without.

Scenarios: ``identity20`` (videotestsrc -> framestamp -> 20 x identity -> fakesink, 16x16
frames: nearly free stages, so the probes' own cost shows) and ``video`` (640x480 frames
through real conversion and scaling stages: a pipeline that does some work per frame).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_probes.py [--frames 2000] [--reps 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

from core.gst import Gst
from probes import native
from probes.tracer import attach

SCENARIOS = {
    "identity20": "videotestsrc num-buffers={frames} ! video/x-raw,width=16,height=16,format=RGB ! framestamp ! "
                  + " ! ".join(f"identity name=i{i}" for i in range(20)) + " ! fakesink sync=false",
    "video": "videotestsrc num-buffers={frames} ! video/x-raw,width=640,height=480,format=I420 ! framestamp ! "
             "videoconvert name=convert ! video/x-raw,format=RGB ! videoscale name=scale ! "
             "video/x-raw,width=320,height=240 ! queue name=queue ! videoflip name=flip method=horizontal-flip ! "
             "fakesink name=sink sync=false",
}
MODES = ("none", "native", "python")


def register_framestamp() -> None:
    from plugins import framestamp

    name, rank, cls = framestamp.__gstelementfactory__
    if Gst.ElementFactory.find(name) is None:
        Gst.Element.register(None, name, rank, cls.__gtype__)


def run_once(description: str, mode: str, frames: int) -> tuple[float, float, int]:
    """(wall s, CPU s, tracepoints per frame) of one run from PLAYING to EOS."""
    pipe = Gst.parse_launch(description.format(frames=frames))
    tracer = None
    if mode != "none":
        tracer = attach(pipe, "bench", backend=mode, capacity=frames * 64)
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
        # Every tracepoint must have fired once per frame, or the cost per tracepoint is wrong.
        if len(events) != frames * points or stats.dropped or stats.unidentified:
            raise SystemExit(f"{mode}: {len(events)} events for {frames} frames x {points} tracepoints, "
                             f"{stats.dropped} dropped, {stats.unidentified} unidentified")
    return wall, cpu, points


def bench(name: str, frames: int, reps: int) -> None:
    description = SCENARIOS[name]
    run_once(description, "native", 20)  # warm-up: plugin loading, first-call costs
    samples = {m: [] for m in MODES}
    points = 0
    for rep in range(reps):
        order = MODES[rep % 3:] + MODES[: rep % 3]
        for mode in order:
            wall, cpu, p = run_once(description, mode, frames)
            samples[mode].append((wall, cpu))
            points = p or points
    wall = {m: statistics.median(w for w, _ in s) for m, s in samples.items()}
    print(f"\n== {name}: {frames} frames, {points} tracepoints per frame, {reps} interleaved repetitions, medians")
    print(f"no-probe time per frame: {wall['none'] / frames * 1e6:.1f} µs")
    print(f"{'mode':8} {'fps':>8} {'lost %':>7} {'µs/tracepoint wall [min..max]':>31} {'µs/tracepoint CPU':>18}")
    print(f"{'none':8} {frames / wall['none']:8.0f}")
    per_point = {}
    for m in MODES[1:]:
        # Paired with the no-probe run of the same repetition: slow drifts of the machine's
        # load cancel out; the spread shows what is left of the noise.
        us_wall = [(w - w0) / (frames * points) * 1e6 for (w, _), (w0, _) in zip(samples[m], samples["none"])]
        us_cpu = [(c - c0) / (frames * points) * 1e6 for (_, c), (_, c0) in zip(samples[m], samples["none"])]
        per_point[m] = (statistics.median(us_wall), statistics.median(us_cpu))
        lost = (1 - wall["none"] / wall[m]) * 100
        spread = f"{per_point[m][0]:.2f} [{min(us_wall):.2f}..{max(us_wall):.2f}]"
        print(f"{m:8} {frames / wall[m]:8.0f} {lost:7.1f} {spread:>31} {per_point[m][1]:18.2f}")
    (nw, nc), (pw, pc) = per_point["native"], per_point["python"]
    if nw > 0 and nc > 0:
        print(f"python / native cost per tracepoint: {pw / nw:.0f}x (wall), {pc / nc:.0f}x (CPU)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--scenario", choices=[*SCENARIOS, "all"], default="all")
    args = parser.parse_args()
    if native.load() is None:
        raise SystemExit(f"native probes unavailable: {native.unavailable_reason()}")
    register_framestamp()
    for name in SCENARIOS if args.scenario == "all" else [args.scenario]:
        bench(name, args.frames, args.reps)


if __name__ == "__main__":
    main()
