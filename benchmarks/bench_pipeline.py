"""Whole-pipeline throughput: frames/s at 1, 2 and 4 sources of 1080p, without and with probes.

    .venv/bin/python benchmarks/bench_pipeline.py [--frames 40] [--repeat 3] [--sources 1,2,4]

Each variant runs the real chain ``sources -> mux -> infer -> tiler -> convert -> osd -> fakesink``
on 1920x1080 test patterns (non-live: as fast as the machine goes), in-process. Variants are
interleaved (repetition-major) so that noise from other work on this shared machine hits all
of them alike; medians are reported. Steady state only: timing starts at the 5th collage.
``--model ssd`` uses the fast SSD person detector instead of CenterNet.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.gst import Gst  # noqa: E402
from pipeline.build import build_pipeline  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.run import Runner  # noqa: E402

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


def measure(sources: int, probes: bool, frames: int, model: str, workdir: Path) -> tuple[float, dict]:
    path = workdir / f"bench-{sources}.yaml"
    path.write_text(config_text(sources, model))
    config = load_config(path)
    built = build_pipeline(config)
    stamps: list[float] = []
    built.sink.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER,
                                               lambda *_: stamps.append(time.perf_counter()) or Gst.PadProbeReturn.OK)
    probing = None
    if probes:
        from probes.instrument import start_probes

        config = replace(config, probes=replace(config.probes, trace=workdir / f"trace-{sources}.jsonl"))
        probing = start_probes(built, config)
    Runner(built, num_frames=frames + WARMUP, progress=None).run()
    info = {}
    if probing is not None:
        info = {"tracepoints": probing.tracer.tracepoints, "dropped": probing.tracer.dropped}
        probing.stop()
    steady = stamps[WARMUP - 1:frames + WARMUP]
    fps_collages = (len(steady) - 1) / (steady[-1] - steady[0])
    return fps_collages * sources, info


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40, help="collages timed per run (after 5 warm-up)")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved repetitions per variant")
    parser.add_argument("--sources", default="1,2,4", help="comma-separated source counts")
    parser.add_argument("--model", choices=sorted(MODELS), default="centernet")
    args = parser.parse_args()
    counts = [int(c) for c in args.sources.split(",")]
    variants = [(n, p) for n in counts for p in (False, True)]
    results: dict[tuple[int, bool], list[float]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeat):
            for n, probes in variants:
                fps, info = measure(n, probes, args.frames, args.model, Path(tmp))
                results[(n, probes)].append(fps)
                extra = f"  ({info['tracepoints']} tracepoints, {info['dropped']} dropped)" if info else ""
                print(f"rep {rep + 1}: {n} source(s) probes={'on ' if probes else 'off'} {fps:7.2f} frames/s{extra}",
                      flush=True)
    print(f"\npipeline frames/s, 1080p sources, model {args.model}, median of {args.repeat} (interleaved)")
    print(f"{'sources':>8} {'no probes':>10} {'probes':>10} {'probes/none':>12} {'vs 1 source':>12}")
    base = statistics.median(results[(counts[0], False)])
    for n in counts:
        off, on = statistics.median(results[(n, False)]), statistics.median(results[(n, True)])
        print(f"{n:>8} {off:>10.2f} {on:>10.2f} {on / off:>12.3f} {off / base:>12.2f}")


if __name__ == "__main__":
    main()
