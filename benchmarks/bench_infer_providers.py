"""The infer element's detector on each ONNX Runtime execution provider: speed and agreement.

Decodes frames of the shipped vtest clip, then runs the detector the ``infer`` element uses
(:class:`dcuscope.plugins.models.Detector`: the same preprocessing, session options and decoders) once
per provider list, side by side with interleaved repetitions, and reports per batch size the
median ms per batch (in all, and in the model alone), frames/s, the ratio to the first provider
list, and whether the detections agree with the first list's (one to one, same class, box
corners within --tolerance px).

    .venv/bin/python benchmarks/bench_infer_providers.py \\
        [--providers CPUExecutionProvider CUDAExecutionProvider,CPUExecutionProvider] \\
        [--model centernet|ssd] [--frames 64] [--batches 1 4] [--repeat 5] [--quick]

A provider list this onnxruntime lacks is reported and left out (GPU providers need the
onnxruntime-gpu package and a GPU); when none is left it says so in one line and exits with
status 2. A figure it cannot produce is ``"n/a (reason)"`` in its JSON (benchmarks/figures.py).
Needs no GStreamer.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.figures import NA, CannotRun, dumps, median, ratio, run  # noqa: E402
from dcuscope.plugins.models import (  # noqa: E402
    DEFAULT_MODEL, Detector, ModelError, inspect_model, open_session, select_providers,
)

MODELS = {"centernet": DEFAULT_MODEL, "ssd": DEFAULT_MODEL.parent / "ssdlite_mobilenetv2_person.onnx"}
CLIP = Path(__file__).resolve().parents[1] / "assets" / "media" / "vtest.avi"
THRESHOLD, IOU = 0.3, 0.5


def read_frames(n: int, start: int = 250) -> list[np.ndarray]:
    """``n`` RGB frames of the shipped clip from frame ``start`` (persons walking in all of them)."""
    cap = cv2.VideoCapture(str(CLIP))
    cap.set(cv2.CAP_PROP_POS_FRAMES, start)
    frames = []
    while len(frames) < n:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    cap.release()
    if len(frames) < n:
        raise CannotRun(f"{CLIP} gave {len(frames)} frames, {n} asked for")
    return frames


@dataclass
class Variant:
    """One provider list: its detector, the session's run time, and the providers ORT really uses."""

    detector: Detector
    timed: TimedSession
    used: list[str]


def run_all(v: Variant, frames: list[np.ndarray], batch: int) -> tuple[float | NA, float | NA, list]:
    """(ms per batch in all, ms per batch in the model, detections per frame) over ``frames``."""
    found = []
    v.timed.ms = 0.0
    t = time.perf_counter()
    for i in range(0, len(frames) - batch + 1, batch):
        found += v.detector.detect(frames[i:i + batch], THRESHOLD, IOU)
    n = len(frames) // batch
    none = f"a batch of {batch} is more than the {len(frames)} frames"
    return ratio(1000 * (time.perf_counter() - t), n, none), ratio(v.timed.ms, n, none), found


def agreement(ref: list, other: list, tol: float) -> dict:
    """Frames whose objects match the reference's one to one: same class, box corners within ``tol`` px."""
    same, worst = 0, 0.0
    for a, b in zip(ref, other):
        if len(a.boxes) != len(b.boxes):
            continue
        unused = set(range(len(b.boxes)))
        ok = True
        for box, cls in zip(a.boxes, a.classes):
            cands = [j for j in unused if b.classes[j] == cls]
            if not cands:
                ok = False
                break
            d = [float(np.abs(box - b.boxes[j]).max()) for j in cands]
            k = int(np.argmin(d))
            worst = max(worst, d[k])
            ok = ok and d[k] <= tol
            unused.discard(cands[k])
        same += ok
    return {"frames_agreeing": same, "frames": len(ref), "max_box_diff_px": round(worst, 3)}


class TimedSession:
    """The session with the time spent in ``run`` (the model alone) added up."""

    def __init__(self, session) -> None:
        self.session, self.ms = session, 0.0

    def run(self, *args, **kwargs):
        t = time.perf_counter()
        try:
            return self.session.run(*args, **kwargs)
        finally:
            self.ms += 1000 * (time.perf_counter() - t)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--providers", nargs="+", default=["CPUExecutionProvider", "CUDAExecutionProvider,CPUExecutionProvider"],
                   help="provider lists to compare, each comma-separated in order of preference; the first is the reference")
    p.add_argument("--model", choices=sorted(MODELS), default="centernet")
    p.add_argument("--frames", type=int, default=64)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--tolerance", type=float, default=1.0, help="px a box may differ from the reference's")
    p.add_argument("--quick", action="store_true", help="a smoke test: model ssd, 4 frames, batches 1 and 2, once")
    args = p.parse_args(argv)
    if args.quick:
        args.model, args.frames, args.batches, args.repeat = "ssd", 4, [1, 2], 1
    if args.frames < 1 or args.repeat < 1 or min(args.batches) < 1:
        p.error("--frames, --repeat and --batches must be at least 1")

    import onnxruntime as ort

    print(dumps({"onnxruntime": ort.__version__, "available": ort.get_available_providers(),
                 "model": args.model}), flush=True)
    frames = read_frames(args.frames)
    variants: dict[str, Variant] = {}
    skipped = []
    for req in args.providers:
        use, missing = select_providers(req)
        if missing:
            why = f"not in this onnxruntime: {', '.join(missing)}"
            skipped.append(f"{req} ({why})")
            print(dumps({"providers": req, "skipped": why}), flush=True)
            continue
        try:
            session = open_session(MODELS[args.model], use)
        except ModelError as exc:
            raise CannotRun(str(exc)) from exc
        timed = TimedSession(session)
        variants[req] = Variant(Detector(timed, inspect_model(session, "auto", MODELS[args.model])), timed,
                                session.get_providers())
    if not variants:
        raise CannotRun(f"no provider list can run here: {'; '.join(skipped)} "
                        f"(available: {', '.join(ort.get_available_providers())})")
    ref = next(iter(variants))
    for batch in args.batches:
        times = {req: [] for req in variants}
        model = {req: [] for req in variants}
        found = {}
        for v in variants.values():  # warm-up: CUDA builds its kernels and arenas on the first runs
            run_all(v, frames[: 2 * batch], batch)
        for _ in range(args.repeat):
            for req, v in variants.items():
                ms, model_ms, found[req] = run_all(v, frames, batch)
                times[req].append(ms)
                model[req].append(model_ms)
        for req, v in variants.items():
            ms = median(times[req])
            ref_ms = median(times[ref])
            print(dumps({
                "providers": req, "used": v.used, "batch": batch, "ms_per_batch": round(ms, 2),
                "model_ms_per_batch": round(median(model[req]), 2),
                "frames_per_s": round(ratio(1000 * batch, ms, "the batches took no time"), 1),
                "speedup_vs_" + ref.split(",")[0]: round(ratio(ref_ms, ms, "the batches took no time"), 2),
                "objects": sum(len(o.boxes) for o in found[req]),
                "agreement": agreement(found[ref], found[req], args.tolerance),
            }), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(run(main))
