"""Runs compared: per stage and end to end, each figure of NEW against BASE with an honest interval.

The document ``dcuscope compare`` prints (table, ``--json``, ``--markdown``), its gate reads and the
page's compare view draws. For each stage (matched by name) and kind (delay, service, wait; end to
end: the frame delay of :mod:`dcuscope.model.delays`) and each input: frames, mean, p50, p90, p99 in
ms; for each input after the first, the change against the first with its 95 % interval from the
circular block bootstrap, its spread corrected for the bias of blocks (:mod:`dcuscope.model.bootstrap`),
over the input's complete frames in the order of their origin.

Verdicts. A figure is *slower* (*faster*) when its whole interval lies above (below) zero and the
change is at least ``noise_pct`` of BASE and ``noise_ms`` (smaller ones are noise however sure:
Criterion's noise threshold); else *no significant change*; a percentile with fewer than
:data:`MIN_TAIL` frames beyond it in a run (p99 of fewer than 1,000 frames) gets *too few frames*.
Each interval is 95 % on its own: among the 40-odd figures of a pipeline about two would cross zero
by chance. The verdict of a whole input is therefore Holm's, which keeps the chance of any false
verdict in the table at 5 %: *slower* when some figure is still slower after Holm's correction
(listed largest change first).

Different pipelines. Where an input's stages differ from BASE's (another config's stage list, an app
with one element more), it is compared with BASE only on the stages both have: a stage only one side
has keeps its figures and no change, and so does the end to end delay, which spans stages only one
side has; their verdicts are withheld (``changes`` is None), and the input's ``apart`` lists them.
A source's stamp (``src2``) only one side has does not make another pipeline: more cameras through
the same stages compare end to end, as the paper's tables of 1, 2 and 3 streams do. An input that
shares no stage with BASE gets the verdict ``not in both``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dcuscope.model.bootstrap import FIGURES, RESAMPLES, Resampled, change, holm, resample
from dcuscope.model.delays import NS_PER_MS, FrameDelays

E2E = "e2e"
"""The row name of the end-to-end frame delay (as gates name it)."""
KINDS = ("delay", "service", "wait")
LEVEL = 0.95
NOISE_PCT = 5.0
NOISE_MS = 0.1
"""Changes smaller than this, or than NOISE_PCT of BASE, get no verdict: a queue's hand-over to its
thread takes tens of µs more in one run than in the next (a wake-up), surely and of no consequence."""
METHOD = ("circular block bootstrap (Politis & Romano) over each run's frames in time order, block length by "
          "Politis & White's rule, each figure's replicates stretched by the block bootstrap's variance bias "
          "(from the run's autocovariances); 95 % percentile intervals of NEW - BASE widened by Student's t with "
          "a degree of freedom a block; input verdicts by Holm's correction")
SLOWER, FASTER, SAME, FEW = "slower", "faster", "no significant change", "too few frames"
APART = "not in both"
"""The verdict of an input that has no figure in common with BASE (no stage of the same name)."""
SOURCE_KIND = "framestamp"
"""The kind of a dcuscope pipeline's per-source stage (``src0``, ``src1``, ... in a header's kinds)."""
MIN_TAIL = 10
"""A percentile needs this many frames beyond it in each run for its interval to mean much (p99: 1,000
frames): with fewer, the resamples' p99 is one of a handful of values, and the interval is lopsided
or wide. Such a figure is shown, its verdict is ``too few frames``, and Holm's family leaves it out."""


@dataclass
class Input:
    """One side of a comparison: a node's frames and where they came from."""

    label: str
    """Short name for column heads, unique among the inputs: the trace's file name, or a stored run's
    :func:`dcuscope.relay.store.runs.run_label` (``session 4 · DCU-1``)."""
    origin: str
    """Where it came from, in full."""
    node: str
    fd: FrameDelays
    kinds: dict[str, str] = field(default_factory=dict)
    """Stage -> its element's factory (TraceHeader.kinds): which stages are sources' stamps."""
    journeys: dict[str, np.ndarray] = field(default_factory=dict)
    """Rows across nodes (:mod:`dcuscope.model.journeys`), name -> ms in time order: the hops the
    node's frames took in or out (``net DCU-1 → DCU-2``) and the journeys ending on it
    (``journey DCU-1 → DCU-2``); compared as delays, after the stages."""


def distinct_labels(labels: list[str]) -> list[str]:
    """``labels`` with a repeated one numbered from its second time: ``session 1 · DCU-1 (2)``."""
    out: list[str] = []
    for label in labels:
        k, name = 1, label
        while name in out:
            k += 1
            name = f"{label} ({k})"
        out.append(name)
    return out


def time_series(fd: FrameDelays) -> dict[tuple[str, str], np.ndarray]:
    """(stage, kind) and (E2E, "delay") -> ms of the complete frames in the order of their origin."""
    c = np.flatnonzero(fd.chains.complete)
    rows = c[np.argsort(fd.table.origin[c], kind="stable")]
    out: dict[tuple[str, str], np.ndarray] = {}
    for s, stage in enumerate(fd.table.stages):
        if not fd.chains.has_exit[s]:
            continue
        for kind in KINDS:
            v = fd.per_stage[kind][rows, s]
            v = v[~np.isnan(v)]
            if len(v):
                out[(stage, kind)] = v / NS_PER_MS
    out[(E2E, "delay")] = fd.delay[rows] / NS_PER_MS
    return out


def compare(inputs: list[Input], resamples: int = RESAMPLES, seed: int = 0, noise_pct: float = NOISE_PCT,
            noise_ms: float = NOISE_MS, progress=None) -> dict:
    """The comparison document of ``inputs`` (the first is BASE); ``progress(done, total)`` is
    called as series are resampled (a long run takes seconds)."""
    if len(inputs) < 2:
        raise ValueError("compare needs at least two inputs")
    rng = np.random.default_rng(seed)
    series = [{**time_series(i.fd), **{(name, "delay"): v for name, v in i.journeys.items()}} for i in inputs]
    keys = _row_keys(inputs, series)
    apart = [_apart(inputs[0], i) for i in inputs]
    total, done = sum(k in s for k in keys for s in series), 0
    seen: list[dict] = [{} for _ in inputs]  # per input, stage -> (its delays, their resamples)
    rows = []
    for stage, kind in keys:
        resampled: list[Resampled | None] = []
        for k, s in enumerate(series):
            v = s.get((stage, kind))
            same = seen[k].get(stage)
            if v is None or len(v) < 2:
                resampled.append(None)
            elif same is not None and np.array_equal(same[0], v):  # service = delay where a stage never waits
                resampled.append(same[1])
            else:
                resampled.append(resample(v, rng, resamples))
                seen[k].setdefault(stage, (v, resampled[-1]))
            done += v is not None
            if progress:
                progress(done, total)
        rows.append(_row(stage, kind, series, resampled, noise_pct, noise_ms, apart))
    return {
        "method": {"interval": METHOD, "level": LEVEL, "resamples": resamples, "seed": seed, "noise_pct": noise_pct,
                   "noise_ms": noise_ms},
        "inputs": [{"label": i.label, "origin": i.origin, "node": i.node, "stages": list(i.fd.table.stages),
                    "apart": a, "frames": int(i.fd.chains.complete.sum()),
                    "incomplete": int((~i.fd.chains.complete).sum())} for i, a in zip(inputs, apart)],
        "stages": list(dict.fromkeys(stage for stage, _ in keys if not any(stage in i.journeys for i in inputs))),
        "rows": rows,
        "verdicts": [None] + [_input_verdict(rows, k) for k in range(1, len(inputs))],
    }


def _row_keys(inputs: list[Input], series: list[dict]) -> list[tuple[str, str]]:
    """Rows in BASE's stage order, then stages only later inputs have; end to end last."""
    stages = list(dict.fromkeys(st for i in inputs for st in i.fd.table.stages))
    keys = [(st, kind) for st in stages for kind in KINDS if any((st, kind) in s for s in series)]
    return keys + [(name, "delay") for name in dict.fromkeys(n for i in inputs for n in i.journeys)] + [(E2E, "delay")]


def _apart(base: Input, other: Input) -> list[str]:
    """The stages only one of ``base`` and ``other`` has, in pipeline order (BASE's first), and E2E
    when they differ in more than sources: what the two are not compared on."""
    mine, theirs = base.fd.table.stages, other.fd.table.stages
    only = [(s, base.kinds) for s in mine if s not in theirs] + [(s, other.kinds) for s in theirs if s not in mine]
    if all(kinds.get(s) == SOURCE_KIND for s, kinds in only):
        return []
    return [s for s, _ in only] + [E2E]


def _row(stage: str, kind: str, series: list[dict], resampled: list[Resampled | None], noise_pct: float,
         noise_ms: float, apart: list[list[str]]) -> dict:
    values, changes = [], []
    for s, r in zip(series, resampled):
        v = s.get((stage, kind))
        values.append(None if r is None else {"frames": len(v), "block": r.block, **r.estimate})
    base = resampled[0]
    for k, r in enumerate(resampled[1:], start=1):
        if base is None or r is None or stage in apart[k]:
            changes.append(None)
            continue
        frames = min(values[0]["frames"], values[k]["frames"])
        few = [f for f in FIGURES if f != "mean" and frames * (1 - int(f[1:]) / 100) < MIN_TAIL]
        changes.append({f: _change_dict(change(base, r, f, LEVEL), noise_pct, noise_ms, f in few) for f in FIGURES})
    return {"stage": stage, "kind": kind, "values": values, "changes": [None] + changes}


def _change_dict(c, noise_pct: float, noise_ms: float, few: bool) -> dict:
    past_noise = (c.pct is None or abs(c.pct) >= noise_pct) and abs(c.delta) >= noise_ms
    verdict = SAME
    if few:
        verdict = FEW
    elif c.low > 0 and past_noise:
        verdict = SLOWER
    elif c.high < 0 and past_noise:
        verdict = FASTER
    return {"delta": c.delta, "low": c.low, "high": c.high, "pct": c.pct, "pct_low": c.pct_low,
            "pct_high": c.pct_high, "p_value": c.p_value, "verdict": verdict}


def _input_verdict(rows: list[dict], k: int) -> dict:
    """Input k against BASE over the whole table, with Holm's correction (see the module docstring)."""
    figures = [(f"{_name(r)}.{f}", c) for r in rows if r["changes"][k] for f, c in r["changes"][k].items()
               if c["verdict"] != FEW]
    kept = holm([c["p_value"] for _, c in figures])
    figures, kept = zip(*sorted(zip(figures, kept), key=lambda fk: -abs(fk[0][1]["delta"]))) if figures else ((), ())
    slower = [name for (name, c), ok in zip(figures, kept) if ok and c["verdict"] == SLOWER]
    faster = [name for (name, c), ok in zip(figures, kept) if ok and c["verdict"] == FASTER]
    verdict = SLOWER if slower else FASTER if faster else SAME
    if not figures:
        verdict = FEW if any(r["changes"][k] for r in rows) else APART
    return {"verdict": verdict, "slower": slower, "faster": faster, "figures": len(figures)}


def _name(row: dict) -> str:
    """A row's name as gates write it: ``infer`` (delay), ``infer.service``, ``e2e``."""
    return row["stage"] if row["kind"] == "delay" else f"{row['stage']}.{row['kind']}"


def find_row(doc: dict, stage: str, kind: str = "delay") -> dict | None:
    """The row of ``stage`` and ``kind`` in a comparison document, None if it has none."""
    return next((r for r in doc["rows"] if r["stage"] == stage and r["kind"] == kind), None)
