"""CPU an inference takes inside a pipeline: ONNX Runtime threads spinning between batches or not.

In a pipeline the detector runs once a batch and the other stages work in between. Here a
batch comes every ``--gap-ms`` (other stages' time, spent sleeping so it costs no CPU), and
the benchmark reports, per model and side by side (interleaved repetitions, medians):
wall time of a run, and CPU time of the process per run (ORT's worker threads included).
The infer element's ``spin-wait`` property (default off) chooses between the two.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_infer_cpu.py [--runs 30] [--repeat 5] [--gap-ms 20] [--quick]

A figure it cannot produce is ``"n/a (reason)"`` in its JSON (benchmarks/figures.py); a model
that cannot be opened is said in one line (exit status 2).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import CannotRun, dumps, median, ratio, run  # noqa: E402
from dcuscope.plugins.models import DEFAULT_MODEL, ModelError, open_session  # noqa: E402

SSD = DEFAULT_MODEL.parent / "ssdlite_mobilenetv2_person.onnx"


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def measure(session, runs: int, gap_s: float) -> tuple[float, float]:
    """(wall ms, CPU ms) per run."""
    i = session.get_inputs()[0]
    shape = [d if isinstance(d, int) and d > 0 else 1 for d in i.shape]
    x = (np.random.default_rng(0).random(shape) * 255).astype(np.uint8 if "uint8" in i.type else np.float32)
    for _ in range(3):
        session.run(None, {i.name: x})
    wall = cpu = 0.0
    for _ in range(runs):
        c, t = _cpu(), time.perf_counter()
        session.run(None, {i.name: x})
        wall += time.perf_counter() - t
        time.sleep(gap_s)
        cpu += _cpu() - c
    return 1000 * wall / runs, 1000 * cpu / runs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=30)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--gap-ms", type=float, default=20.0)
    p.add_argument("--quick", action="store_true", help="a smoke test: the SSD model only, 2 runs, 1 repetition")
    args = p.parse_args(argv)
    models = (SSD, DEFAULT_MODEL)
    if args.quick:
        models, args.runs, args.repeat = (SSD,), 2, 1
    if args.runs < 1 or args.repeat < 1 or args.gap_ms < 0:
        p.error("--runs and --repeat must be at least 1, --gap-ms not negative")
    for model in models:
        try:
            sessions = {spin: open_session(model, ["CPUExecutionProvider"], spin_wait=spin) for spin in (False, True)}
        except ModelError as exc:
            raise CannotRun(str(exc)) from exc
        got = {spin: [] for spin in sessions}
        for _ in range(args.repeat):
            for spin, session in sessions.items():
                got[spin].append(measure(session, args.runs, args.gap_ms / 1000))
        med = {spin: (median(w for w, _ in v), median(c for _, c in v)) for spin, v in got.items()}
        no_cpu = "the runs without spinning took no CPU time that getrusage could see"
        print(dumps({
            "model": model.name, "gap_ms": args.gap_ms,
            "no_spin": {"wall_ms": round(med[False][0], 1), "cpu_ms": round(med[False][1], 1)},
            "spin": {"wall_ms": round(med[True][0], 1), "cpu_ms": round(med[True][1], 1)},
            "cpu_ratio_spin_vs_no_spin": round(ratio(med[True][1], med[False][1], no_cpu), 2),
            "wall_ratio_spin_vs_no_spin": round(ratio(med[True][0], med[False][0], "the runs took no time"), 2),
        }), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(run(main))
