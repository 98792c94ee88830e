"""``dcuscope compare --fail-if``: bounds on a comparison's changes, for CI.

A bound reads ``STAGE[.KIND].FIGURE OP VALUE``: ``infer.p99 > +5%``, ``e2e.p50 > +2ms``,
``infer.service.mean > +0.5ms``, ``convert.wait.p90 >= 10%``; KIND is delay (the default),
service or wait, FIGURE mean, p50, p90 or p99, OP one of > >= < <=, VALUE in ms, us, s or % of
BASE. A bound *fails* only when the whole confidence interval of the change is past it: a change
that may be inside it (noise) passes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dcuscope.core.errors import DcuscopeError
from dcuscope.model.bootstrap import FIGURES
from dcuscope.model.compare import KINDS, find_row

_BOUND = re.compile(r"^\s*(?P<metric>[^<>=\s]+)\s*(?P<op>>=|<=|>|<)\s*(?P<value>[+-]?(\d+(\.\d*)?|\.\d+))\s*"
                    r"(?P<unit>%|ms|us|µs|s)\s*$")
TO_MS = {"ms": 1.0, "us": 1e-3, "µs": 1e-3, "s": 1e3}


def split_bound(text: str, relative: bool = True) -> re.Match | None:
    """The parts of ``METRIC OP VALUE UNIT`` (``--fail-if`` here, ``--slo`` of capacity), or None:
    ``relative`` allows a signed VALUE and the unit %, a change against a base."""
    m = _BOUND.match(text)
    if m is None or not relative and (m["value"][0] in "+-" or m["unit"] == "%"):
        return None
    return m


@dataclass(frozen=True)
class Bound:
    text: str
    stage: str
    kind: str
    figure: str
    op: str
    value: float
    """ms, or % of BASE when ``percent``."""
    percent: bool


def parse_bound(text: str) -> Bound:
    """A ``--fail-if`` bound, or a DcuscopeError that shows the form."""
    m = split_bound(text)
    if not m:
        raise DcuscopeError(f"--fail-if {text!r}: expected STAGE[.KIND].FIGURE OP VALUE, e.g. \"infer.p99 > +5%\" or "
                            "\"e2e.p50 > +2ms\" (OP: > >= < <=; VALUE in %, ms, us or s)")
    stage, kind, figure = metric_parts(m["metric"])
    if not stage or figure not in FIGURES:
        raise DcuscopeError(f"--fail-if {text!r}: the figure must be one of {', '.join(FIGURES)} after a stage name "
                            "(or e2e), e.g. infer.p99")
    percent = m["unit"] == "%"
    value = float(m["value"]) * (1.0 if percent else TO_MS[m["unit"]])
    return Bound(text=text.strip(), stage=stage, kind=kind, figure=figure, op=m["op"], value=value, percent=percent)


def metric_parts(metric: str) -> tuple[str, str, str]:
    """``infer.service.p99`` -> (stage, kind, figure): ("infer", "service", "p99"); KIND defaults to
    delay (``e2e.p50`` -> ("e2e", "delay", "p50")); a stage name may hold dots. Unchecked."""
    parts = metric.split(".")
    has_kind = len(parts) >= 3 and parts[-2] in KINDS
    return ".".join(parts[:-2] if has_kind else parts[:-1]), parts[-2] if has_kind else "delay", parts[-1]


@dataclass
class Outcome:
    bound: Bound
    input: str
    failed: bool
    reason: str
    """One line: the bound, the change and its interval, and the input."""


def check(doc: dict, bound: Bound) -> list[Outcome]:
    """The bound against every input after BASE; a DcuscopeError when the document cannot say."""
    row = find_row(doc, bound.stage, bound.kind)
    if row is None:
        names = ", ".join(doc["stages"] + ["e2e"])
        raise DcuscopeError(f"--fail-if {bound.text!r}: no {bound.kind} of stage {bound.stage!r} in the inputs "
                            f"(stages: {names})")
    out = []
    for k, inp in enumerate(doc["inputs"][1:], start=1):
        c = row["changes"][k]
        if c is None and bound.stage in inp["apart"]:
            raise DcuscopeError(f"--fail-if {bound.text!r}: {inp['label']} and BASE are different pipelines (not in "
                                f"both: {', '.join(inp['apart'])}): they are compared only on the stages both have")
        if c is None:
            raise DcuscopeError(f"--fail-if {bound.text!r}: {inp['label']} or BASE has no {bound.kind} of "
                                f"{bound.stage!r} to compare")
        c = c[bound.figure]
        if bound.percent:
            if c["pct"] is None:
                raise DcuscopeError(f"--fail-if {bound.text!r}: BASE's {bound.figure} is 0 ms, no change in %: "
                                    "give the bound in ms")
            est, low, high, unit, digits = c["pct"], c["pct_low"], c["pct_high"], "%", 1
        else:
            est, low, high, unit, digits = c["delta"], c["low"], c["high"], " ms", 3
        failed = {">": low > bound.value, ">=": low >= bound.value,
                  "<": high < bound.value, "<=": high <= bound.value}[bound.op]
        why = "the whole interval is past the bound" if failed else "the interval reaches inside the bound"
        reason = (f"{'FAILED' if failed else 'passed'}: {bound.text}: {inp['label']} vs {doc['inputs'][0]['label']} "
                  f"{est:+.{digits}f}{unit} [{low:+.{digits}f}, {high:+.{digits}f}]: {why}")
        out.append(Outcome(bound=bound, input=inp["label"], failed=failed, reason=reason))
    return out
