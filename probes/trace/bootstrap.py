"""Confidence intervals for figures of autocorrelated series: the circular block bootstrap.

Frames of one run are not independent: a frame that waited behind a slow one is slow too, and
a busy machine slows a stretch of frames at once. An interval that treats them as independent
(the plain bootstrap, or a t-interval over frames) is too narrow, the more so the stronger the
correlation. The circular block bootstrap (Politis & Romano 1992) resamples the series in blocks
of consecutive frames, so that each block keeps the correlation inside it; the block length is
chosen from the series itself by the rule of Politis & White (2004), with the correction of
Patton, Politis & White (2009). ``tests/probes/trace/test_bootstrap.py`` checks the coverage on
AR(1) series of known correlation, where a plain bootstrap misses.

Two runs are independent of each other: each is resampled on its own, and the interval of a
difference is the percentile interval of the differences of the resampled figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

QUANTILES = (50, 90, 99)
FIGURES = ("mean",) + tuple(f"p{q}" for q in QUANTILES)
"""What each resample yields: the mean and these percentiles (numpy's linear method)."""
RESAMPLES = 1000
CHUNK_VALUES = 4_000_000
"""Values gathered at once while resampling (32 MB of float64)."""


def block_length(x: np.ndarray) -> int:
    """The circular block bootstrap's block length for ``x``, by Politis & White's rule.

    The autocorrelations up to the first lag after which ``K_N`` in a row are insignificant
    give the bandwidth M; flat-top lag windows then estimate the quantities whose ratio is the
    optimal length, ``(2 G^2 / D)^(1/3) n^(1/3)``, with ``D = 4/3 g(0)^2`` for circular blocks.
    1 for a series without correlation; at most n / 3 (three blocks, else nothing is resampled).
    """
    n = len(x)
    if n < 8:
        return 1
    xc = x - x.mean()
    var = float(xc @ xc) / n
    if var == 0:
        return 1
    max_lag = min(n - 1, math.ceil(math.sqrt(n)) + 5)
    spectrum = np.fft.rfft(xc, 2 * n)
    acov = np.fft.irfft(spectrum * np.conj(spectrum))[: max_lag + 1] / n
    rho = acov / acov[0]
    k_n = max(5, math.ceil(math.sqrt(math.log10(n))))
    bound = 2.0 * math.sqrt(math.log10(n) / n)
    small = np.abs(rho[1:]) < bound
    m_hat = max_lag
    for m in range(0, max_lag - k_n + 1):
        if small[m:m + k_n].all():
            m_hat = m
            break
    big_m = min(2 * max(m_hat, 1), max_lag)
    k = np.arange(-big_m, big_m + 1)
    t = np.abs(k) / big_m
    window = np.where(t <= 0.5, 1.0, np.where(t <= 1.0, 2.0 * (1.0 - t), 0.0))
    r = acov[np.abs(k)]
    g = float((window * np.abs(k) * r).sum())
    d = 4.0 / 3.0 * float((window * r).sum()) ** 2
    if d <= 0 or g == 0:
        return 1
    b = (2.0 * g * g / d) ** (1.0 / 3.0) * n ** (1.0 / 3.0)
    return int(min(max(1, math.ceil(b)), max(1, n // 3)))


@dataclass
class Resampled:
    """A figure of a series and its values over the resamples."""

    block: int
    """Block length used (frames)."""
    estimate: dict[str, float]
    """Figure (:data:`FIGURES`) -> its value on the series itself."""
    replicates: dict[str, np.ndarray]
    """Figure -> (resamples,) its values on the resampled series."""


def figures(x: np.ndarray, axis: int = -1, quantiles=QUANTILES) -> dict[str, np.ndarray]:
    """The mean and percentiles of ``x`` along ``axis``."""
    q = np.percentile(x, quantiles, axis=axis, method="linear")
    return {"mean": x.mean(axis=axis), **{f"p{p}": q[i] for i, p in enumerate(quantiles)}}


def resample(x: np.ndarray, rng: np.random.Generator, resamples: int = RESAMPLES, block: int | None = None,
             quantiles=QUANTILES) -> Resampled:
    """Circular block bootstrap of ``x`` (in time order): its figures and their replicates.

    Each resample joins ceil(n / b) blocks of b consecutive values, starting anywhere (wrapping
    around the end), cut to n values. ``block`` 1 is the plain bootstrap (for comparison only).
    """
    x = np.asarray(x, np.float64)
    n = len(x)
    if n == 0:
        raise ValueError("no values to resample")
    if x.min() == x.max():  # a stage that never waits: every resample is the series itself
        names = ["mean"] + [f"p{q}" for q in quantiles]
        return Resampled(block=1, estimate={f: float(x[0]) for f in names},
                         replicates={f: np.full(resamples, x[0]) for f in names})
    b = block_length(x) if block is None else max(1, min(int(block), n))
    n_blocks = -(-n // b)
    offsets = np.arange(b)
    out = {f: np.empty(resamples) for f in ["mean"] + [f"p{q}" for q in quantiles]}
    per_chunk = max(1, CHUNK_VALUES // n)
    for lo in range(0, resamples, per_chunk):
        hi = min(resamples, lo + per_chunk)
        starts = rng.integers(0, n, size=(hi - lo, n_blocks))
        idx = ((starts[:, :, None] + offsets) % n).reshape(hi - lo, n_blocks * b)[:, :n]
        for f, v in figures(x[idx], axis=1, quantiles=quantiles).items():
            out[f][lo:hi] = v
    return Resampled(block=b, estimate={f: float(v) for f, v in figures(x, quantiles=quantiles).items()}, replicates=out)


def interval(r: Resampled, figure: str, level: float = 0.95) -> tuple[float, float]:
    """PLACEHOLDER percentile interval of one run's figure."""
    tail = (1.0 - level) / 2 * 100
    low, high = np.percentile(r.replicates[figure], (tail, 100 - tail))
    return float(low), float(high)


@dataclass
class Change:
    """NEW against BASE for one figure: the difference and its ratio, with percentile intervals."""

    base: float
    new: float
    delta: float
    low: float
    high: float
    pct: float | None
    pct_low: float | None
    pct_high: float | None
    p_value: float
    """Two-sided, from the normal approximation of the bootstrap distribution of the difference
    (fine enough for Holm's correction, which needs p-values far below 1 / resamples)."""


def change(base: Resampled, new: Resampled, figure: str, level: float = 0.95) -> Change:
    """NEW - BASE of ``figure``, its ``level`` interval, and the same in % of BASE."""
    tail = (1.0 - level) / 2 * 100
    b0, n0 = base.estimate[figure], new.estimate[figure]
    d = new.replicates[figure] - base.replicates[figure]
    low, high = np.percentile(d, (tail, 100 - tail))
    pct = pct_low = pct_high = None
    if b0 > 0 and (base.replicates[figure] > 0).all():
        ratio = (new.replicates[figure] / base.replicates[figure] - 1.0) * 100
        pct = (n0 / b0 - 1.0) * 100
        pct_low, pct_high = (float(v) for v in np.percentile(ratio, (tail, 100 - tail)))
    sd = float(d.std(ddof=1))
    delta = n0 - b0
    p = 1.0 if sd == 0 and delta == 0 else (0.0 if sd == 0 else math.erfc(abs(delta) / sd / math.sqrt(2)))
    return Change(base=b0, new=n0, delta=delta, low=float(low), high=float(high), pct=pct, pct_low=pct_low,
                  pct_high=pct_high, p_value=p)


def holm(p_values: list[float], alpha: float = 0.05) -> list[bool]:
    """Which hypotheses Holm's step-down procedure rejects, keeping the family-wise error <= alpha."""
    order = sorted(range(len(p_values)), key=p_values.__getitem__)
    rejected = [False] * len(p_values)
    for rank, i in enumerate(order):
        if p_values[i] > alpha / (len(p_values) - rank):
            break
        rejected[i] = True
    return rejected
