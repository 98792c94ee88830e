"""The figures a benchmark reports, and the reason for each one a run could not produce.

A run can fail to produce a figure: too short for two samples in its window, no frame pushed
to the client, a provider missing, a denominator of zero. Such a figure is an :class:`NA`
that carries its reason. It goes through arithmetic and the statistics below as NaN would
(``100 * NA(why)`` is ``NA(why)``), and prints, formats and dumps to JSON as
``n/a (reason)``, so no benchmark crashes on missing data and none shows a bare dash.

Where reasons would make a table unreadable, :class:`Notes` puts ``n/a [1]`` in the cell and
``n/a [1]: reason`` under the table.

A benchmark that cannot run at all here (no Chromium, no Prometheus, no usable provider, a
relay that does not start) raises :class:`CannotRun`; :func:`run` turns it into one line on
stderr and exit status 2, without a traceback.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np


class NA:
    """A figure that a run could not produce, and why. False in a test; arithmetic on it gives it back."""

    __slots__ = ("reason",)

    def __init__(self, reason: str) -> None:
        self.reason = one_line(reason) or "no reason given"

    def __str__(self) -> str:
        return f"n/a ({self.reason})"

    def __repr__(self) -> str:
        return f"NA({self.reason!r})"

    def __format__(self, spec: str) -> str:  # f"{x:.1f}" works whether x is a figure or not
        return str(self)

    def __bool__(self) -> bool:
        return False

    def __eq__(self, other: object) -> bool:
        return isinstance(other, NA) and other.reason == self.reason

    def __hash__(self) -> int:
        return hash(("NA", self.reason))

    def _same(self, *_args: Any) -> NA:
        return self

    __add__ = __radd__ = __sub__ = __rsub__ = __mul__ = __rmul__ = _same
    __truediv__ = __rtruediv__ = __floordiv__ = __rfloordiv__ = __pow__ = __rpow__ = _same
    __neg__ = __pos__ = __abs__ = __round__ = _same


Figure = float | int | NA


def one_line(text: str) -> str:
    """``text`` on one line: its lines joined, runs of blanks squeezed."""
    return " ".join(str(text).split())


def missing(x: Any) -> bool:
    """Whether ``x`` is no figure: NA, None or NaN."""
    return x is None or isinstance(x, NA) or (isinstance(x, (float, np.floating)) and math.isnan(x))


def known(x: Any, reason: str) -> Figure:
    """``x``, or ``NA(reason)`` when it is None or NaN (an NA keeps its own reason)."""
    if isinstance(x, NA):
        return x
    return NA(reason) if missing(x) else x


def _split(values: Iterable[Any], empty: str) -> tuple[list, NA]:
    """The figures among ``values``, and the NA to give when there are none: the reasons of the
    values that were NA (each once), else ``empty``."""
    present, reasons = [], []
    for v in values:
        if isinstance(v, NA):
            reasons.append(v.reason)
        elif not missing(v):
            present.append(v)
    return present, NA("; ".join(dict.fromkeys(reasons)) if reasons else empty)


def median(values: Iterable[Any], empty: str = "no value to take the median of") -> Figure:
    """The median of the figures among ``values``; NA when there is none."""
    present, none = _split(values, empty)
    return statistics.median(present) if present else none


def mean(values: Iterable[Any], empty: str = "no value to average") -> Figure:
    present, none = _split(values, empty)
    return statistics.fmean(present) if present else none


def percentile(values: Iterable[Any], q: float, empty: str = "no value to take a percentile of") -> Figure:
    """The ``q``-th percentile (0-100, linear) of the figures among ``values``; NA when there is none."""
    present, none = _split(values, empty)
    return float(np.percentile(np.asarray(present, dtype=np.float64), q)) if present else none


def minimum(values: Iterable[Any], empty: str = "no value") -> Figure:
    present, none = _split(values, empty)
    return min(present) if present else none


def maximum(values: Iterable[Any], empty: str = "no value") -> Figure:
    present, none = _split(values, empty)
    return max(present) if present else none


def ratio(num: Any, den: Any, zero: str = "division by zero", missing_reason: str = "not measured") -> Figure:
    """``num / den``; NA(``zero``) when ``den`` is 0, an NA operand's own NA, NA(``missing_reason``) for None/NaN."""
    for x in (num, den):
        if missing(x):
            return known(x, missing_reason)
    return NA(zero) if den == 0 else num / den


def fmt(x: Any, spec: str = "", unit: str = "", why: str = "not measured") -> str:
    """``x`` formatted with ``spec`` and ``unit``, or ``n/a (reason)`` (``why`` for None/NaN)."""
    x = known(x, why)
    return str(x) if isinstance(x, NA) else f"{x:{spec}}{unit}"


class Notes:
    """Footnotes for the n/a cells of a table: ``cell`` gives ``n/a [k]``, ``lines`` the reasons."""

    def __init__(self) -> None:
        self._keys: dict[str, int] = {}

    def cell(self, x: Any, spec: str = "", unit: str = "", why: str = "not measured") -> str:
        x = known(x, why)
        if not isinstance(x, NA):
            return f"{x:{spec}}{unit}"
        k = self._keys.setdefault(x.reason, len(self._keys) + 1)
        return f"n/a [{k}]"

    def lines(self) -> list[str]:
        """``n/a [k]: reason`` per footnote given out, in order."""
        return [f"n/a [{k}]: {reason}" for reason, k in self._keys.items()]

    def __bool__(self) -> bool:
        return bool(self._keys)


def _json_default(x: Any) -> Any:
    if isinstance(x, NA):
        return str(x)
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"{type(x).__name__} is not JSON serializable")


def dumps(obj: Any, **kwargs: Any) -> str:
    """``json.dumps`` where every NA is the string ``n/a (reason)``."""
    return json.dumps(obj, default=_json_default, **kwargs)


class CannotRun(Exception):
    """The benchmark cannot run here (a program, a device, a service missing): one line, no traceback."""


def run(main: Callable[[], int | None], name: str | None = None) -> int:
    """``main()``'s exit status; a :class:`CannotRun` becomes one line on stderr and status 2."""
    try:
        return main() or 0
    except CannotRun as exc:
        print(f"{name or Path(sys.argv[0]).name}: cannot run: {one_line(str(exc))}", file=sys.stderr, flush=True)
        return 2


def last_line(text: str | bytes) -> str:
    """The last non-blank line of a process's output (an error's message, not its traceback)."""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else "(no output)"
