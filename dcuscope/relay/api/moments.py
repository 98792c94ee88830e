"""The same moment across DCUs: two nodes' frames of one camera matched by capture time.

When two DCUs consume the same RTSP stream (the paper's high-availability pair), each frame
reaches both with the same capture time: the camera's RTCP sender reports map its RTP
timestamp to the camera's clock (``timestamp/x-ntp``, :mod:`dcuscope.protocol.events` point ``capture``),
and both receivers get the same timestamps and the same reports. Matching the two nodes'
complete frames by that time pairs the frames that show one moment; comparing their ends,
each moved to the relay's clock by its run's :class:`dcuscope.relay.clock.correction.Correction`, says which DCU
finished that moment first and by how much. The error bar of a difference is the sum of both
nodes' clock uncertainties at the two end timestamps: each correction is true within its bound.

Capture times are the camera's clock and are never corrected here (a node's clock correction
says nothing about the camera's clock): matching needs only that both nodes read the same one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dcuscope.model.delays import FrameDelays
from dcuscope.model.frametable import MISSING
from dcuscope.relay.clock.correction import UNKNOWN_BOUND, Correction
from dcuscope.relay.errors import RelayError

MATCH_TOLERANCE_NS = 1_000_000
"""Two capture times within 1 ms are one moment. Both receivers map the same RTP timestamp
through the same sender reports, so one frame's capture times agree to well under a
microsecond (rounding of the 90 kHz RTP clock and the 64-bit NTP time); consecutive frames of a
camera are at least 4 ms apart (240 frames/s), so 1 ms never pairs a frame with its neighbour,
and leaves room for a receiver that mapped a frame with an older sender report."""
DEFAULT_LIMIT = 200
MAX_LIMIT = 2000
RTSP_SCHEMES = ("rtsp://", "rtsps://", "rtspt://", "rtspu://")
"""Sources whose frames carry a capture time (rtspsrc's ``add-reference-timestamp-meta``, pipeline.sources)."""


class MomentsError(RelayError):
    """Two nodes' moments cannot be compared as asked (the message says why)."""


@dataclass(frozen=True)
class NodeFrames:
    """One node's complete frames of one source that have a capture time, by capture time."""

    node: str
    source: int
    frame: np.ndarray
    capture: np.ndarray
    """(n,) int64 ns on the camera's clock (as received, never corrected)."""
    origin: np.ndarray
    """(n,) int64 ns on the relay's clock (corrected)."""
    end: np.ndarray
    """(n,) int64 ns on the relay's clock (corrected)."""
    uncertainty: np.ndarray
    """(n,) int64 ns: the bound of the node's correction at each end."""
    clock: str
    """The correction applied (:attr:`Correction.applied`)."""


def node_frames(node: str, fd: FrameDelays, source: int, corr: Correction) -> NodeFrames:
    """The complete frames of ``source`` in ``fd`` that have a capture time, sorted by it."""
    t, ch = fd.table, fd.chains
    rows = np.flatnonzero(ch.complete & (t.source == source) & (t.capture != MISSING))
    rows = rows[np.argsort(t.capture[rows], kind="stable")]
    end = ch.end[rows]
    return NodeFrames(node, source, t.frame[rows], t.capture[rows], corr.correct(t.origin[rows]), corr.correct(end),
                      corr.uncertainties(end), corr.applied)


def _nearest(sorted_values: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index into ``sorted_values`` (not empty) of the value nearest each of ``values``."""
    if len(sorted_values) == 1:
        return np.zeros(len(values), np.int64)
    j = np.clip(np.searchsorted(sorted_values, values), 1, len(sorted_values) - 1)
    left = np.abs(values - sorted_values[j - 1]) <= np.abs(sorted_values[j] - values)
    return np.where(left, j - 1, j)


def match(a: np.ndarray, b: np.ndarray, tolerance_ns: int = MATCH_TOLERANCE_NS) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (rows of ``a``, rows of ``b``) of sorted capture times that are each other's nearest
    and within ``tolerance_ns``: one-to-one, so a frame never stands for two moments."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    to_b = _nearest(b, a)
    to_a = _nearest(a, b)
    ia = np.arange(len(a))
    ok = (to_a[to_b] == ia) & (np.abs(a - b[to_b]) <= tolerance_ns)
    return ia[ok], to_b[ok]


def shared_sources(a: dict[int, str], b: dict[int, str], uri: str | None = None) -> list[tuple[int, int, str]]:
    """(source id on a, on b, URI) of every URI both run headers name (``header.sources``), or of
    ``uri`` only; MomentsError when there is none."""
    if uri is not None:
        pick = {v for v in (uri, f"uri:{uri}") if v in a.values() and v in b.values()}
        if not pick:
            raise MomentsError(f"source {uri[:200]!r} is not a source of both nodes (a: {_listed(a)}; b: {_listed(b)})")
    else:
        pick = set(a.values()) & set(b.values())
        if not pick:
            raise MomentsError(f"the two nodes share no source (a: {_listed(a)}; b: {_listed(b)}): name one "
                               "with source=URI, or source_a=ID&source_b=ID")
    by_uri_b = {v: k for k, v in b.items()}
    return [(k, by_uri_b[v], v) for k, v in sorted(a.items()) if v in pick]


def _listed(sources: dict[int, str], most: int = 8) -> str:
    """A header's sources for an error message, the first ``most`` of them."""
    items = [f"{k}={v[:120]}" for k, v in sorted(sources.items())[:most]]
    return ", ".join(items) + (f", ... ({len(sources)} in all)" if len(sources) > most else "") or "none"


def _ms(ns) -> float:
    return float(ns) / 1e6


def _side(f: NodeFrames, k: int) -> dict:
    return {"frame": int(f.frame[k]), "origin": int(f.origin[k]), "end": int(f.end[k]),
            "uncertainty_ns": int(f.uncertainty[k])}


def _moment(fa: NodeFrames, fb: NodeFrames, i: int, j: int, uri: str) -> dict:
    diff = int(fb.end[j] - fa.end[i])
    error = int(fa.uncertainty[i] + fb.uncertainty[j])
    return {"capture": int(fa.capture[i]), "source": uri, "a": _side(fa, i), "b": _side(fb, j),
            "diff_ms": _ms(diff), "error_ms": _ms(error),
            "first": fa.node if diff > 0 else fb.node if diff < 0 else None, "significant": abs(diff) > error}


def summary(a: str, b: str, diff_ns: np.ndarray, error_ns: np.ndarray, known: bool) -> dict:
    """Aggregate of matched moments: the difference (end of b - end of a), the share each node
    finished first, and whether the mean difference exceeds the clocks' error bar.

    The error bars bound systematic clock errors, not noise: averaging does not shrink them, but
    the mean of bounded errors is bounded by the mean of the bounds, the bar the mean is judged by.
    """
    n = len(diff_ns)
    if n == 0:
        return {"matched": 0, "diff_ms": None, "error_ms": None, "first_share": {a: None, b: None},
                "significant": None, "verdict": None}  # compare says why (none_matched)
    mean, bar = float(diff_ns.mean()), float(error_ns.mean())
    p50, p95 = np.percentile(diff_ns, [50, 95])
    stats = {"mean": mean / 1e6, "p50": float(p50) / 1e6, "p95": float(p95) / 1e6,
             "min": _ms(diff_ns.min()), "max": _ms(diff_ns.max())}
    significant = abs(mean) > bar if known else None
    return {"matched": n, "diff_ms": stats, "error_ms": {"mean": bar / 1e6, "max": _ms(error_ns.max())},
            "first_share": {a: float((diff_ns > 0).mean()), b: float((diff_ns < 0).mean())},
            "significant_moments": int((np.abs(diff_ns) > error_ns).sum()), "significant": significant,
            "verdict": _verdict(a, b, n, mean, bar, significant)}


def none_matched(a: str, b: str, uris: list[str], frames: dict[str, int], tolerance_ns: int) -> str:
    """Why no moment matched, and what would make one: ``frames``, each node's complete frames of
    the shared sources ``uris`` that carry a capture time."""
    if not frames[a] and not frames[b]:
        if not any(_rtsp(u) for u in uris):
            return ("no capture times: moments match the frames of one camera on two DCUs by its capture time, which "
                    "an RTSP camera's RTCP sender reports give (docs/relay.md, \"The same moment on two DCUs\"); "
                    f"{', '.join(_shown(u) for u in uris)} {'is' if len(uris) == 1 else 'are'} not RTSP, and files "
                    "and test sources have none")
        return ("no capture time yet: an RTSP camera's frames carry one once its first RTCP sender report came "
                "(within seconds of the stream's start)")
    for side, other in ((a, b), (b, a)):
        if not frames[side]:
            return (f"{side} has no frame with a capture time of the shared cameras yet ({other} has {frames[other]}): "
                    "moments need both DCUs' frames of one moment")
    return (f"none of {a}'s {frames[a]} and {b}'s {frames[b]} frames with a capture time match within "
            f"{tolerance_ns / 1e6:g} ms: the two DCUs hold frames of different moments (one of them started later, "
            "or the URI names two different cameras)")


def _rtsp(uri: str) -> bool:
    """Whether a run header's source (``uri:rtsp://...``) is an RTSP stream, whose frames get capture times."""
    return uri.removeprefix("uri:").lower().startswith(RTSP_SCHEMES)


def _shown(uri: str, most: int = 80) -> str:
    """A source as a message names it: its URI without the header's ``uri:``, the end kept if long."""
    u = uri.removeprefix("uri:")
    return u if len(u) <= most else "…" + u[-most:]


def _verdict(a: str, b: str, n: int, mean: float, bar: float, significant: bool | None) -> str:
    if mean == 0:
        return f"neither node finished first on average over {n} moments"
    told = f"{a if mean > 0 else b} finished first by {abs(mean) / 1e6:.3f} ms on average over {n} moments"
    if significant is None:
        return f"{told}; a node's clock bound is not known yet: not judged"
    within = "beyond" if significant else "within"
    return f"{told}, {within} the clocks' error bar (±{bar / 1e6:.3f} ms): {'' if significant else 'not '}significant"


@dataclass(frozen=True)
class Side:
    """What one node contributes: its name, its run header's sources, its complete frames and
    its run's correction."""

    node: str
    sources: dict[int, str]
    fd: FrameDelays
    corr: Correction


def pairs_of(a: Side, b: Side, uri: str | None = None,
             ids: tuple[int, int] | None = None) -> list[tuple[NodeFrames, NodeFrames, str]]:
    """The frames to match, per source: the sources both name by URI (or ``uri`` only), or the
    source ids ``ids`` (on a, on b) given explicitly; MomentsError when there is none."""
    if ids is not None:
        for side, sid in zip((a, b), ids):
            if sid not in side.sources:
                raise MomentsError(f"node {side.node!r} has no source {sid} (its sources: {_listed(side.sources)})")
        chosen = [(ids[0], ids[1], a.sources[ids[0]])]
    else:
        chosen = shared_sources(a.sources, b.sources, uri)
    return [(node_frames(a.node, a.fd, sa, a.corr), node_frames(b.node, b.fd, sb, b.corr), name)
            for sa, sb, name in chosen]


def compare(pairs: list[tuple[NodeFrames, NodeFrames, str]], limit: int = DEFAULT_LIMIT,
            tolerance_ns: int = MATCH_TOLERANCE_NS) -> dict:
    """Moments of two nodes over sources (``(a's frames, b's frames, URI)`` each): the newest
    ``limit`` moments by capture time, and the aggregate over every matched one."""
    fa0, fb0 = pairs[0][0], pairs[0][1]
    a, b = fa0.node, fb0.node
    moments, diffs, errors, spread = [], [], [], 0
    unmatched = {a: 0, b: 0}
    frames = {a: 0, b: 0}
    for fa, fb, uri in pairs:
        ia, jb = match(fa.capture, fb.capture, tolerance_ns)
        frames[a] += len(fa.capture)
        frames[b] += len(fb.capture)
        unmatched[a] += len(fa.capture) - len(ia)
        unmatched[b] += len(fb.capture) - len(jb)
        diffs.append(fb.end[jb] - fa.end[ia])
        errors.append(fa.uncertainty[ia] + fb.uncertainty[jb])
        if len(ia):
            spread = max(spread, int(np.abs(fa.capture[ia] - fb.capture[jb]).max()))
        moments.extend((int(fa.capture[i]), fa, fb, int(i), int(j), uri) for i, j in zip(ia, jb))
    moments.sort(key=lambda m: m[0])
    known = all(f.clock not in UNKNOWN_BOUND for p in pairs for f in p[:2])
    agg = summary(a, b, np.concatenate(diffs), np.concatenate(errors), known)
    if not agg["matched"]:
        agg["verdict"] = none_matched(a, b, [uri for _, _, uri in pairs], frames, tolerance_ns)
    return {"a": a, "b": b, "clock": {a: fa0.clock, b: fb0.clock}, "tolerance_ms": tolerance_ns / 1e6,
            "sources": [{"uri": uri, "a": fa.source, "b": fb.source} for fa, fb, uri in pairs],
            "summary": dict(agg, unmatched=unmatched, frames=frames, capture_spread_us=spread / 1e3),
            "moments": [_moment(fa, fb, i, j, uri) for _, fa, fb, i, j, uri in moments[-limit:]]}
