"""Bounds on one stream count, and the answer over all of them.

A bound reads as compare's (``dcuscope.gate``), with an absolute value: ``STAGE[.KIND].FIGURE OP
VALUE``, e.g. ``e2e.p99 <= 200ms``, ``infer.mean <= 60ms``, ``infer.service.p95 < 40ms``; KIND is
delay (the default), service or wait, FIGURE mean, p50, p90, p95 or p99, OP <= < >= >, VALUE in
ms, us or s. The frame rate is a bound too: the slowest stream keeps at least ``floor`` of its
source's rate.

A bound *holds* at a count when its whole 95 % interval is inside it, *fails* when the whole
interval is outside, and is *undecided* when the interval straddles it: the run was too short to
tell, and the answer says so rather than guess. A count passes when every bound holds.
"""

from __future__ import annotations

from dataclasses import dataclass

from dcuscope.capacity.measure import CountFigures, Estimate, stage_estimate
from dcuscope.core.errors import UsageError
from dcuscope.gate import TO_MS, metric_parts, split_bound
from dcuscope.model.compare import E2E

FIGURES = ("mean", "p50", "p90", "p95", "p99")
HOLDS, FAILS, UNDECIDED = "holds", "fails", "undecided"
_SYMBOL = {"<=": "≤", ">=": "≥", "<": "<", ">": ">"}


@dataclass(frozen=True)
class Slo:
    text: str
    stage: str
    kind: str
    figure: str
    op: str
    value_ms: float

    def short(self) -> str:
        kind = "" if self.kind == "delay" else f".{self.kind}"
        return f"{self.stage}{kind}.{self.figure} {_SYMBOL[self.op]} {self.value_ms:g} ms"


def parse_slo(text: str) -> Slo:
    """A ``--slo`` bound, or a UsageError that shows the form."""
    m = split_bound(text, relative=False)
    if not m:
        raise UsageError(f"--slo {text!r}: expected STAGE[.KIND].FIGURE OP VALUE, e.g. \"e2e.p99 <= 200ms\" or "
                         "\"infer.mean <= 60ms\" (OP: <= < >= >; VALUE in ms, us or s)")
    stage, kind, figure = metric_parts(m["metric"])
    if not stage or figure not in FIGURES:
        raise UsageError(f"--slo {text!r}: the figure must be one of {', '.join(FIGURES)} after a stage name (or e2e), "
                         "e.g. e2e.p99")
    if stage == E2E and kind != "delay":
        raise UsageError(f"--slo {text!r}: e2e has a delay only (no service or wait)")
    return Slo(text=text.strip(), stage=stage, kind=kind, figure=figure, op=m["op"],
               value_ms=float(m["value"]) * TO_MS[m["unit"]])


@dataclass
class Check:
    what: str
    """The bound, as the answer says it: ``e2e.p99 ≤ 200 ms``, ``fps ≥ 27 (90 % of 30)``."""
    outcome: str
    detail: str
    """The figure and its interval: ``e2e.p99 212.0 ms [195.1, 230.2]``."""


def check_slo(slo: Slo, figures: CountFigures) -> Check:
    est = stage_estimate(figures, slo.stage, slo.kind, slo.figure)
    if est is None:
        return Check(slo.short(), FAILS, f"no {slo.kind} of {slo.stage} in this run (stages: "
                                          f"{', '.join(figures.stages) or 'none'})")
    return Check(slo.short(), _outcome(est, slo.op, slo.value_ms), f"{_name(slo)} {_interval(est, ' ms')}")


def check_fps(figures: CountFigures, floor: float, rate: float | None) -> Check:
    """The slowest stream keeps ``floor`` (a fraction) of ``rate``."""
    if rate is None:
        return Check(f"fps ≥ {floor * 100:g} % of the source's rate", UNDECIDED,
                     "the sources' frame rate is unknown (their caps said none): give the sources a rate:")
    need = floor * rate
    what = f"fps ≥ {need:.3g} ({floor * 100:g} % of {rate:g})"
    if figures.fps is None:
        return Check(what, FAILS, "a stream brought fewer than 3 frames through the pipeline after the warm-up")
    return Check(what, _outcome(figures.fps, ">=", need), f"slowest stream {_interval(figures.fps, ' fps', 1)}")


def _outcome(est: Estimate, op: str, bound: float) -> str:
    inside = {"<=": lambda v: v <= bound, "<": lambda v: v < bound,
              ">=": lambda v: v >= bound, ">": lambda v: v > bound}[op]
    if inside(est.low) and inside(est.high):
        return HOLDS
    if not inside(est.low) and not inside(est.high):
        return FAILS
    return UNDECIDED


def _name(slo: Slo) -> str:
    return f"{slo.stage}{'' if slo.kind == 'delay' else '.' + slo.kind}.{slo.figure}"


def _interval(est: Estimate, unit: str, digits: int = 1) -> str:
    return f"{est.value:.{digits}f}{unit} [{est.low:.{digits}f}, {est.high:.{digits}f}]"


def outcome(checks: list[Check]) -> str:
    """A count's: fails if any bound fails, else undecided if any is, else holds."""
    found = {c.outcome for c in checks}
    return FAILS if FAILS in found else UNDECIDED if UNDECIDED in found else HOLDS


def answer(counts: list[dict], max_streams: int, stopped: str | None = None) -> tuple[int | None, str]:
    """(capacity, the one-line answer) from the counts' documents, in order (each with ``streams``,
    ``outcome``, ``checks`` and ``limiting``); ``stopped`` says why the search ended early (Ctrl-C).
    The capacity is None when not even 1 stream was decided (undecided, a run that failed, or none run)."""
    passed = 0
    for c in counts:
        if c["outcome"] != HOLDS:
            break
        passed = c["streams"]
    first = counts[0] if counts else None
    unknown = first is None or (first["outcome"] != HOLDS and (first["outcome"] == UNDECIDED or not first["checks"]))
    head = "capacity unknown" if unknown else f"capacity {passed} stream{'s' if passed != 1 else ''}"
    if passed:
        held = next(c for c in counts if c["streams"] == passed)
        head += f": {' and '.join(ch['what'] for ch in held['checks'])} hold at {passed} with 95 % confidence"
    nxt = next((c for c in counts if c["streams"] == passed + 1), None)
    if nxt is None:
        tail = stopped or (f"--max-streams {max_streams} reached: it may take more" if passed >= max_streams else "")
    elif nxt["outcome"] == UNDECIDED:
        open_ = [ch["detail"] for ch in nxt["checks"] if ch["outcome"] == UNDECIDED]
        tail = f"undecided at {passed + 1}: run longer (--duration) ({'; '.join(open_)})"
    elif nxt.get("error"):
        tail = f"at {passed + 1} the run failed: {nxt['error']}"
    else:
        failed = [ch for ch in nxt["checks"] if ch["outcome"] == FAILS]
        tail = f"at {passed + 1} " + "; ".join(f"{ch['what'].split(' (')[0]} fails ({ch['detail']})" for ch in failed)
        neck = nxt.get("limiting")
        if neck and neck.get("utilization") is not None:
            thread = neck.get("thread_utilization")
            shared = f", its thread {thread:.0%}" if thread is not None and thread >= neck["utilization"] + 0.005 else ""
            tail += (f"; {neck['stage']} {'saturates' if neck.get('saturated') else 'limits'} "
                     f"(utilization {neck['utilization']:.0%}{shared})")
    return None if unknown else passed, head + (f"; {tail}" if tail else "")
