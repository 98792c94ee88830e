"""Confidence intervals for figures of autocorrelated series: the circular block bootstrap, corrected.

Frames of one run are not independent: a frame that waited behind a slow one is slow too, and
a busy machine slows a stretch of frames at once. An interval that treats them as independent
(the plain bootstrap, or a t-interval over frames) is too narrow, the more so the stronger the
correlation. The circular block bootstrap (Politis & Romano 1992) resamples the series in blocks
of consecutive frames, so that each block keeps the correlation inside it; the block length is
chosen from the series itself by the rule of Politis & White (2004), with the correction of
Patton, Politis & White (2009).

Even so its spread falls short, for two reasons that do not vanish at the lengths of a run
(uncorrected, the mean's 95 % interval held the truth about 90 % of the time at phi = 0.9).
Blocks cut the correlation across their ends, and the series is centred on its own mean: at the
rule's length the replicates' variance is 10-15 % short whatever the correlation. So each figure's
replicates are stretched about their mean by :func:`stretch`, the factor that undoes it, from the
series' autocovariances (those of the series for the mean, of ``x <= the percentile`` for a
percentile: its influence, less correlated in a tail than the series). And the spread is itself an
estimate from n / b blocks, lowest when the mean is furthest off: intervals are widened by
Student's t with a degree of freedom a block (:func:`widening`). ``tests/model/test_bootstrap.py``
checks the coverage on AR(1) series of known correlation, Gaussian and log-normal, where a plain
bootstrap misses; ``benchmarks/bench_coverage.py`` tabulates it against the uncorrected method.

Two runs are independent of each other: each is resampled on its own, and the interval of a
difference is the (widened) percentile interval of the differences of the resampled figures; that
of one run's figure (:func:`interval`) the (widened) percentile interval of its replicates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

QUANTILES = (50, 90, 99)
FIGURES = ("mean",) + tuple(f"p{q}" for q in QUANTILES)
"""What each resample yields by default: the mean and these percentiles (numpy's linear method)."""
RESAMPLES = 1000
CHUNK_VALUES = 4_000_000
"""Values gathered at once while resampling (32 MB of float64)."""


def _flat_top(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Lags k and the flat-top lag window w(k) over them for ``x`` (Politis & White), with its
    autocovariances R(k); None for a constant series.

    The autocorrelations up to the first lag after which ``K_N`` in a row are insignificant give
    the bandwidth M; the window is flat to M / 2 and falls linearly to 0 at M.
    """
    n = len(x)
    xc = x - x.mean()
    if float(xc @ xc) == 0:
        return None
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
    return k, window, acov[np.abs(k)]


def block_length(x: np.ndarray) -> int:
    """The circular block bootstrap's block length for ``x``, by Politis & White's rule.

    The flat-top estimates of ``G = sum |k| R(k)`` and ``g(0) = sum R(k)`` give the optimal length,
    ``(2 G^2 / D)^(1/3) n^(1/3)``, with ``D = 4/3 g(0)^2`` for circular blocks.
    1 for a series without correlation; at most n / 3 (three blocks, else nothing is resampled).
    """
    n = len(x)
    ft = _flat_top(x) if n >= 8 else None
    if ft is None:
        return 1
    k, window, r = ft
    g = float((window * np.abs(k) * r).sum())
    d = 4.0 / 3.0 * float((window * r).sum()) ** 2
    if d <= 0 or g == 0:
        return 1
    b = (2.0 * g * g / d) ** (1.0 / 3.0) * n ** (1.0 / 3.0)
    return int(min(max(1, math.ceil(b)), max(1, n // 3)))


MAX_STRETCH = 2.0
"""The variance correction of :func:`stretch` is kept within 1 / 2 and 2 (a short or odd series)."""


def stretch(x: np.ndarray, block: int) -> float:
    """The factor by which the circular block bootstrap with blocks of ``block`` frames understates the
    spread of ``x``'s mean (1 for a constant or short series).

    Resampled in blocks of b, the mean's variance is ``sum (1 - |k| / b) Rc(k) / n`` over |k| < b, Rc
    the series' circular autocovariances; the truth is the long-run variance over n, estimated with the
    flat-top window of :func:`block_length` and divided by ``1 - sum w / n`` (each R(k) is short by
    about the long-run variance over n, for the centring on the series' own mean). The factor is the
    square root of their ratio.
    """
    n = len(x)
    ft = _flat_top(x) if n >= 8 else None
    if ft is None:
        return 1.0
    _, window, r = ft
    long_run = float((window * r).sum()) / max(1.0 - float(window.sum()) / n, 0.5)
    xc = x - x.mean()
    spectrum = np.fft.rfft(xc)
    rc = np.fft.irfft(spectrum * np.conj(spectrum), n)[:block] / n
    kept = rc[0] + 2.0 * float(((1.0 - np.arange(1, block) / block) * rc[1:]).sum())
    if long_run <= 0 or kept <= 0:
        return 1.0
    return math.sqrt(min(MAX_STRETCH, max(1.0 / MAX_STRETCH, long_run / kept)))


@dataclass
class Resampled:
    """A figure of a series and its values over the resamples."""

    block: int
    """Block length used (frames)."""
    estimate: dict[str, float]
    """Figure (:data:`FIGURES`, or those of the ``quantiles`` asked) -> its value on the series itself."""
    replicates: dict[str, np.ndarray]
    """Figure -> (resamples,) its values on the resampled series."""
    blocks: float = math.inf
    """Blocks of the series (n / block) that the replicates' spread rests on, for :func:`widening`; inf
    where no widening is due (a given block: the uncorrected bootstrap; a constant series)."""


def names(quantiles: tuple[int, ...] = QUANTILES) -> tuple[str, ...]:
    """The figures of :func:`figures` with these ``quantiles``: ``("mean", "p50", ...)``."""
    return ("mean",) + tuple(f"p{q}" for q in quantiles)


def figures(x: np.ndarray, axis: int = -1, quantiles: tuple[int, ...] = QUANTILES) -> dict[str, np.ndarray]:
    """The mean and ``quantiles`` percentiles of ``x`` along ``axis``."""
    q = np.percentile(x, quantiles, axis=axis, method="linear")
    return {"mean": x.mean(axis=axis), **{f"p{p}": q[i] for i, p in enumerate(quantiles)}}


def resample(x: np.ndarray, rng: np.random.Generator, resamples: int = RESAMPLES, block: int | None = None,
             quantiles: tuple[int, ...] = QUANTILES) -> Resampled:
    """Circular block bootstrap of ``x`` (in time order): its figures and their replicates.

    Each resample joins ceil(n / b) blocks of b consecutive values, starting anywhere (wrapping
    around the end), cut to n values. With ``block`` None, b is Politis & White's and each figure's
    replicates are then stretched about their mean by :func:`stretch` of its influence series (the
    series for the mean, ``x <= the percentile`` for a percentile; see the module docstring). A given
    ``block`` gives the uncorrected bootstrap of that length (1: the plain bootstrap), for comparison:
    neither stretched nor widened by :func:`change` and :func:`interval`.
    """
    x = np.asarray(x, np.float64)
    n = len(x)
    if n == 0:
        raise ValueError("no values to resample")
    figs = names(quantiles)
    if x.min() == x.max():  # a stage that never waits: every resample is the series itself
        return Resampled(block=1, estimate={f: float(x[0]) for f in figs},
                         replicates={f: np.full(resamples, x[0]) for f in figs})
    b = block_length(x) if block is None else max(1, min(int(block), n))
    n_blocks = -(-n // b)
    offsets = np.arange(b)
    out = {f: np.empty(resamples) for f in figs}
    per_chunk = max(1, CHUNK_VALUES // n)
    for lo in range(0, resamples, per_chunk):
        hi = min(resamples, lo + per_chunk)
        starts = rng.integers(0, n, size=(hi - lo, n_blocks))
        idx = ((starts[:, :, None] + offsets) % n).reshape(hi - lo, n_blocks * b)[:, :n]
        for f, v in figures(x[idx], axis=1, quantiles=quantiles).items():
            out[f][lo:hi] = v
    estimate = {f: float(v) for f, v in figures(x, quantiles=quantiles).items()}
    if block is None:
        for f, v in out.items():
            influence = x if f == "mean" else (x <= estimate[f]).astype(np.float64)
            out[f] = _widened(v, stretch(influence, b))
    return Resampled(block=b, estimate=estimate, replicates=out, blocks=n / b if block is None else math.inf)


def interval(r: Resampled, figure: str, level: float = 0.95) -> tuple[float, float]:
    """The ``level`` interval of one run's ``figure``: the percentile interval of its replicates, widened
    by :func:`widening`.

    For a bound on one run (``e2e.p99 <= 200 ms``) rather than a change between two; ``r`` from
    :func:`resample` with the rule's block (its default), whose replicates carry the correction.
    """
    tail = (1.0 - level) / 2 * 100
    low, high = np.percentile(_widened(r.replicates[figure], widening(r.blocks, level)), (tail, 100 - tail))
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


def widening(blocks: float, level: float) -> float:
    """Student's t over the normal quantile of a ``level`` interval, with ``blocks - 1`` degrees of freedom.

    The replicates' spread is an estimate from n / b blocks, and it is low when the series' mean is far
    from the truth (the long excursion that moved the mean is what the blocks cut): the percentile
    interval, normal in effect, falls short by about what Student's t adds with one degree of freedom
    a block (as Kiefer & Vogelsang's fixed-b critical values for the Bartlett window, the block
    bootstrap's). t by its Cornish-Fisher expansion.
    """
    if not math.isfinite(blocks):
        return 1.0
    nu = max(blocks - 1.0, 2.0)
    z = NormalDist().inv_cdf(0.5 + level / 2)
    t = (z + (z ** 3 + z) / (4 * nu) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * nu ** 2)
         + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * nu ** 3))
    return t / z


def _widened(v: np.ndarray, factor: float) -> np.ndarray:
    """``v`` stretched about its mean by ``factor``, within the range it reached.

    Replicates can be skewed or bimodal: a run with one stall has a p99 with the stall in a resample
    or out, and a stage that sleeps at least 20 ms, a few times much longer, a mean that no resample
    puts under 20 ms. Stretched about their mean, such replicates left the range that any resample
    gave (a p99 interval reaching below the p50; a mean below 20 ms)."""
    centre = v.mean()
    return np.clip(centre + factor * (v - centre), v.min(), v.max())


def change(base: Resampled, new: Resampled, figure: str, level: float = 0.95) -> Change:
    """NEW - BASE of ``figure``, its ``level`` interval, and the same in % of BASE.

    The interval is the percentile interval of the replicates' differences, widened by
    :func:`widening` of the run with fewer blocks.
    """
    tail = (1.0 - level) / 2 * 100
    wide = widening(min(base.blocks, new.blocks), level)
    b0, n0 = base.estimate[figure], new.estimate[figure]
    d = _widened(new.replicates[figure] - base.replicates[figure], wide)
    low, high = np.percentile(d, (tail, 100 - tail))
    pct = pct_low = pct_high = None
    if b0 > 0 and (base.replicates[figure] > 0).all():
        ratio = _widened((new.replicates[figure] / base.replicates[figure] - 1.0) * 100, wide)
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
