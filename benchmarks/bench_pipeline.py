"""Whole-pipeline throughput: frames/s at 1, 2 and 4 sources of 1080p, without and with probes.

    .venv/bin/python benchmarks/bench_pipeline.py [--frames 40] [--repeat 3] [--sources 1,2,4] [--quick]

Each variant runs the real chain ``sources -> mux -> infer -> tiler -> convert -> osd -> fakesink``
on 1920x1080 test patterns (non-live: as fast as the machine goes), in-process. Variants are
interleaved (repetition-major) so that noise from other work on this shared machine hits all
of them alike; medians are reported. Steady state only: timing starts at the 5th collage.
``--model ssd`` uses the fast SSD person detector instead of CenterNet. A run that fails or
ends too soon is ``n/a (reason)`` in every figure that needs it (benchmarks/figures.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, Figure, Notes, fmt, median, ratio, run  # noqa: E402
from dcuscope.core.errors import DcuscopeError  # noqa: E402
from dcuscope.core.gst import Gst  # noqa: E402
from dcuscope.pipeline.build import build_pipeline  # noqa: E402
from dcuscope.pipeline.config import load_config  # noqa: E402
from dcuscope.pipeline.run import Runner  # noqa: E402

WARMUP = 5
MODELS = {"centernet": "centernet_mobilenetv3_coco80.onnx", "ssd": "ssdlite_mobilenetv2_person.onnx"}


def config_text(sources: int, model: str) -> str:
    cols = 2 if sources > 1 else 1
    rows = (sources + cols - 1) // cols
    patterns = ["smpte", "ball", "snow", "pinwheel"]
    srcs = "\n".join(f"  - {{test: {patterns[i % 4]}, width: 1920, height: 1080, rate: 30}}" for i in range(sources))
    return f"""\
sources:
{srcs}
stages:
  - mux: {{batch-size: {sources}, width: 1920, height: 1080}}
  - infer: {{model: {ROOT / 'assets' / 'models' / MODELS[model]}}}
  - tiler: {{rows: {rows}, columns: {cols}, width: 1920, height: 1080}}
  - convert: {{format: RGBA}}
  - osd: {{}}
sink: {{type: fake}}
"""


def measure(sources: int, probes: bool, frames: int, model: str, workdir: Path) -> tuple[Figure, dict]:
    """Frames/s summed over sources, and the probes' counts; NA with the error for a run that failed."""
    try:
        return _measure(sources, probes, frames, model, workdir)
    except DcuscopeError as exc:
        return NA(f"the run failed: {exc}"), {}


def _measure(sources: int, probes: bool, frames: int, model: str, workdir: Path) -> tuple[Figure, dict]:
    path = workdir / f"bench-{sources}.yaml"
    path.write_text(config_text(sources, model))
    config = load_config(path)
    built = build_pipeline(config)
    stamps: list[float] = []
    built.sink.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER,
                                               lambda *_: stamps.append(time.perf_counter()) or Gst.PadProbeReturn.OK)
    probing = None
    if probes:
        from dcuscope.probes.instrument import start_probes

        config = replace(config, probes=replace(config.probes, trace=workdir / f"trace-{sources}.jsonl"))
        probing = start_probes(built, config)
    Runner(built, num_frames=frames + WARMUP, progress=None).run()
    info = {}
    if probing is not None:
        info = {"tracepoints": probing.tracer.tracepoints, "dropped": probing.tracer.dropped}
        probing.stop()
    steady = stamps[WARMUP - 1:frames + WARMUP]
    if len(steady) < 2:
        return NA(f"{len(stamps)} collages reached the sink: too few for two after the {WARMUP - 1} of warm-up"), info
    fps_collages = ratio(len(steady) - 1, steady[-1] - steady[0], "the collages reached the sink all at once")
    return fps_collages * sources, info


def table(results: dict[tuple[int, bool], list[Figure]], counts: list[int]) -> list[str]:
    """Per source count: medians without and with probes, their ratio, and the rate against the
    first count's; an n/a cell is ``n/a [k]``, its reason under the table."""
    notes = Notes()
    widths = (10, 10, 12, 12)
    lines = [f"{'sources':>8} {'no probes':>10} {'probes':>10} {'probes/none':>12} {f'vs {counts[0]} source':>12}"]
    base = median(results[(counts[0], False)], "no run")
    for n in counts:
        off, on = median(results[(n, False)], "no run"), median(results[(n, True)], "no run")
        cells = [(off, ".2f"), (on, ".2f"), (ratio(on, off), ".3f"), (ratio(off, base), ".2f")]
        lines.append(f"{n:>8} " + " ".join(f"{notes.cell(x, spec):>{w}}" for (x, spec), w in zip(cells, widths)))
    return lines + notes.lines()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40, help="collages timed per run (after 5 warm-up)")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved repetitions per variant")
    parser.add_argument("--sources", default="1,2,4", help="comma-separated source counts")
    parser.add_argument("--model", choices=sorted(MODELS), default="centernet")
    parser.add_argument("--quick", action="store_true", help="a smoke test: 1 source, model ssd, 3 collages, once")
    args = parser.parse_args(argv)
    if args.quick:
        args.frames, args.repeat, args.sources, args.model = 3, 1, "1", "ssd"
    try:
        counts = [int(c) for c in args.sources.split(",")]
    except ValueError:
        parser.error(f"--sources {args.sources!r}: give comma-separated counts, e.g. 1,2,4")
    if args.frames < 1 or args.repeat < 1 or not counts or min(counts) < 1:
        parser.error("--frames, --repeat and every source count must be at least 1")
    model_file = ROOT / "assets" / "models" / MODELS[args.model]
    if not model_file.is_file():
        raise CannotRun(f"model file {model_file} does not exist")
    variants = [(n, p) for n in counts for p in (False, True)]
    results: dict[tuple[int, bool], list[Figure]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeat):
            for n, probes in variants:
                fps, info = measure(n, probes, args.frames, args.model, Path(tmp))
                results[(n, probes)].append(fps)
                extra = f"  ({info['tracepoints']} tracepoints, {info['dropped']} dropped)" if info else ""
                print(f"rep {rep + 1}: {n} source(s) probes={'on ' if probes else 'off'} "
                      f"{fmt(fps, '7.2f', ' frames/s')}{extra}", flush=True)
    print(f"\npipeline frames/s, 1080p sources, model {args.model}, median of {args.repeat} (interleaved)")
    print("\n".join(table(results, counts)))
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
