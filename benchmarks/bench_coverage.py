"""Coverage of ``dcuscope compare``'s intervals on synthetic runs, the uncorrected block bootstrap beside the corrected one.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_coverage.py [--runs 400] [--frames 3000] [--phi 0.7 0.9]

Each run is an AR(1) series of frames, x[t] = phi x[t-1] + e[t] with e ~ N(0, 1), started in its
stationary law: ``gaussian`` frames are 10 + x ms, ``lognormal`` ones 10 exp(s x) ms with s such
that the log has a standard deviation of 1 (a delay's tail: p99 ten times the median). NEW is BASE + 2 ms, so every figure's true
change is 2 ms; a row gives the share of ``--runs`` pairs whose 95 % interval of the change holds
it, and the intervals' mean width. ``old`` is what compare used before issue 49: the circular block
bootstrap with Politis & White's block length, uncorrected; ``new`` is
:func:`dcuscope.model.bootstrap.resample` as it is. Both see the same runs.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from dcuscope.model.bootstrap import FIGURES, block_length, change, resample  # noqa: E402

SHIFT = 2.0
NOISES = ("gaussian", "lognormal")


def ar1(rng: np.random.Generator, runs: int, n: int, phi: float) -> np.ndarray:
    """(runs, n) stationary AR(1) series with N(0, 1) innovations."""
    e = rng.standard_normal((runs, n))
    x = np.empty((runs, n))
    x[:, 0] = e[:, 0] / math.sqrt(1 - phi * phi)
    for t in range(1, n):
        x[:, t] = phi * x[:, t - 1] + e[:, t]
    return x


def frames(x: np.ndarray, noise: str, phi: float) -> np.ndarray:
    return 10 + x if noise == "gaussian" else 10 * np.exp(x * math.sqrt(1 - phi * phi))


def old(x: np.ndarray, rng: np.random.Generator, resamples: int):
    """Compare's bootstrap before issue 49: the rule's block length, replicates as they come."""
    return resample(x, rng, resamples, block=block_length(x))


def new(x: np.ndarray, rng: np.random.Generator, resamples: int):
    return resample(x, rng, resamples)


def coverage(method, base: np.ndarray, news: np.ndarray, resamples: int, seed: int) -> tuple[dict, dict]:
    """Per figure: the share of pairs whose interval holds SHIFT, and the intervals' mean width."""
    rng = np.random.default_rng(seed)
    hits, widths = dict.fromkeys(FIGURES, 0), {f: [] for f in FIGURES}
    for b, n in zip(base, news):
        rb, rn = method(b, rng, resamples), method(n, rng, resamples)
        for f in FIGURES:
            c = change(rb, rn, f)
            hits[f] += c.low <= SHIFT <= c.high
            widths[f].append(c.high - c.low)
    return {f: h / len(base) for f, h in hits.items()}, {f: float(np.mean(w)) for f, w in widths.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=400, help="pairs of runs per row (default %(default)d)")
    parser.add_argument("--frames", type=int, default=3000, help="frames per run (default %(default)d)")
    parser.add_argument("--phi", type=float, nargs="+", default=[0.7, 0.9], help="AR(1) coefficients (default 0.7 0.9)")
    parser.add_argument("--resamples", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=49)
    args = parser.parse_args()
    if args.runs < 1 or args.frames < 30 or args.resamples < 10 or not all(0 <= p < 1 for p in args.phi):
        parser.error("--runs >= 1, --frames >= 30, --resamples >= 10 and 0 <= --phi < 1")
    t0 = time.perf_counter()
    rows = []
    for phi in args.phi:
        for noise in NOISES:
            rng = np.random.default_rng([args.seed, round(phi * 100), NOISES.index(noise)])
            base = frames(ar1(rng, args.runs, args.frames, phi), noise, phi)
            news = frames(ar1(rng, args.runs, args.frames, phi), noise, phi) + SHIFT
            for name, method in (("old", old), ("new", new)):
                rows.append((name, phi, noise, *coverage(method, base, news, args.resamples, args.seed)))
    se = math.sqrt(0.95 * 0.05 / args.runs) * 100
    print(f"{args.runs} pairs of {args.frames:,} frames per row, {args.resamples} resamples, 95 % intervals of "
          f"NEW - BASE (true: {SHIFT:g} ms); a true 95 % shows with a standard error of {se:.1f} points\n")
    print("| method | φ | noise | " + " | ".join(FIGURES) + " | " + " | ".join(f"{f} width (ms)" for f in FIGURES) + " |")
    print("|---|---|---|" + "---|" * (2 * len(FIGURES)))
    for name, phi, noise, cov, width in sorted(rows, key=lambda r: (r[0] != "old", r[1], r[2])):
        print(f"| {name} | {phi:g} | {noise} | " + " | ".join(f"{cov[f] * 100:.1f} %" for f in FIGURES) + " | "
              + " | ".join(f"{width[f]:.3g}" for f in FIGURES) + " |")
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
