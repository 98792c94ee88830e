"""The comparison document (:mod:`dcuscope.model.compare`) as a terminal table or Markdown.

Per stage and kind a block: one line per input with frames, mean, p50, p90, p99 in ms; under
each input after BASE, the change of each figure in ms and in % of BASE with the 95 % interval of
the % (of the ms where BASE is 0), marked ``▲`` slower or ``▼`` faster where that is the verdict;
``not in both`` where one side lacks the stage (or, for end to end, the pipelines' stages differ).
"""

from __future__ import annotations

import math

from dcuscope.model.bootstrap import FIGURES
from dcuscope.model.compare import APART, E2E, FEW, MIN_TAIL, SAME, SLOWER

NEVER_WAIT_MS = 0.001
MARK = {SLOWER: " ▲", SAME: "", "faster": " ▼", FEW: " ?"}


LEGEND = ("change: NEW - BASE in ms, then in % of BASE with its 95 % interval; "
          "▲ slower, ▼ faster: 95 % interval entirely past 0 and the change at least the noise threshold; "
          f"? too few frames: under {MIN_TAIL} beyond that percentile in a run (p99 of under 1,000 frames)")


def _title(row: dict) -> str:
    if row["stage"] == E2E:
        return "end to end (frame delay)"
    return f"{row['stage']} ({row['kind']})" if row["kind"] != "delay" else row["stage"]


def _change(c: dict) -> str:
    """``+2.049 ms +96.2% [+95.1, +97.3] ▲``: the ms as precise as the values, so that it reads as the
    difference of the two lines above it."""
    if c["pct"] is not None:
        text = f"{_ms(c['delta'])} ms {c['pct']:+.1f}% [{c['pct_low']:+.1f}, {c['pct_high']:+.1f}]"
    else:
        text = f"{_ms(c['delta'])} ms [{_ms(c['low'])}, {_ms(c['high'])}]"
    return text + MARK[c["verdict"]]


def ms_digits(v: float) -> int:
    """Decimals for ``v`` ms: to the µs, more below 0.1 ms so that it keeps 3 significant digits (an
    element of a few µs reads 0.00213, not 0.002), to the ns at most."""
    return 3 if v == 0 or abs(v) >= 0.1 else max(3, min(6, 2 - math.floor(math.log10(abs(v)))))


def _ms(v: float) -> str:
    return f"{v:+.{ms_digits(v)}f}"


def _value(v: dict | None, figure: str) -> str:
    return "-" if v is None else f"{v[figure]:.{ms_digits(v[figure])}f}"


def never_wait(doc: dict) -> list[str]:
    """Stages whose frames never wait (p99 of wait under 1 µs in every input): service = delay."""
    return [r["stage"] for r in doc["rows"] if r["kind"] == "wait"
            and all(v is None or v["p99"] < NEVER_WAIT_MS for v in r["values"])]


def blocks(doc: dict) -> list[tuple[str, list[list[str]]]]:
    """(title, lines of cells: name, frames, mean, p50, p90, p99) per row of the document; the
    service and wait rows of stages that never wait are left out (they repeat the delay)."""
    labels = [i["label"] for i in doc["inputs"]]
    skip = set(never_wait(doc))
    out = []
    for row in doc["rows"]:
        if row["kind"] != "delay" and row["stage"] in skip:
            continue
        lines = []
        for k, (label, v) in enumerate(zip(labels, row["values"])):
            lines.append([label, "-" if v is None else str(v["frames"])] + [_value(v, f) for f in FIGURES])
            if k:
                c = row["changes"][k]
                cells = [""] * len(FIGURES) if c is None else [_change(c[f]) for f in FIGURES]
                lines.append(["  not in both" if c is None else "  change", ""] + cells)
        out.append((_title(row), lines))
    return out


def _head(doc: dict) -> list[str]:
    lines = []
    for k, i in enumerate(doc["inputs"]):
        role = "BASE" if k == 0 else "NEW " if len(doc["inputs"]) == 2 else f"NEW{k}"
        lines.append(f"{role} {i['label']}: {i['origin']}, {i['frames']} complete frames"
                     + (f" ({i['incomplete']} incomplete)" if i["incomplete"] else ""))
    return lines


def verdict_lines(doc: dict) -> list[str]:
    """Per input after BASE its verdict over the whole table (Holm), naming the figures."""
    out = []
    base = doc["inputs"][0]["label"]
    for k, (i, v) in enumerate(zip(doc["inputs"][1:], doc["verdicts"][1:]), start=1):
        if i["apart"]:
            shared = shared_stages(doc, k)
            out.append(f"{i['label']} vs {base}: different pipelines, compared on the {len(shared)} stage"
                       f"{'' if len(shared) == 1 else 's'} both have; not in both, no verdict: "
                       f"{', '.join(_stage_name(s) for s in i['apart'])}")
        if v["verdict"] == APART:
            out.append(f"{i['label']} vs {base}: nothing to compare (no stage in both)")
            continue
        named = v["slower"] or v["faster"]
        what = f": {', '.join(named[:6])}{' ...' if len(named) > 6 else ''}" if named else ""
        out.append(f"{i['label']} vs {base}: {v['verdict'].upper() if v['verdict'] != SAME else v['verdict']}{what} "
                   f"({v['figures']} figures, family-wise 5 %)")
    return out


def shared_stages(doc: dict, k: int) -> list[str]:
    """The stages input k is compared with BASE on (a row of each with a change)."""
    return list(dict.fromkeys(r["stage"] for r in doc["rows"] if r["changes"][k] and r["stage"] != E2E))


def _stage_name(stage: str) -> str:
    return "end to end" if stage == E2E else stage


def method_line(doc: dict) -> str:
    m = doc["method"]
    return (f"intervals: {m['interval']}; {m['resamples']} resamples; changes under {m['noise_pct']:g}% of BASE "
            f"or {m['noise_ms']:g} ms count as noise")


def format_table(doc: dict) -> str:
    """Aligned text for a terminal."""
    heads = ["", "frames"] + [f"{f} ms" for f in FIGURES]
    body = blocks(doc)
    widths = [max(len(heads[c]), *(len(cells[c]) for _, lines in body for cells in lines)) for c in range(len(heads))]
    widths[0] = max(widths[0], *(len(t) for t, _ in body))

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(widths[0]) if j == 0 else c.rjust(widths[j]) for j, c in enumerate(cells)).rstrip()

    out = _head(doc) + [""]
    for title, lines in body:
        out.append(line([title] + heads[1:]))
        out += ["  " + line(cells) for cells in lines]
        out.append("")
    out += verdict_lines(doc)
    out += _skipped(doc)
    out.append(LEGEND)
    out.append(method_line(doc))
    return "\n".join(out) + "\n"


def _skipped(doc: dict) -> list[str]:
    stages = never_wait(doc)
    return [f"service = delay, wait 0 (not shown): {', '.join(stages)}"] if stages else []


def format_markdown(doc: dict) -> str:
    """A Markdown table for a pull-request comment."""
    out = ["### dcuscope compare", ""]
    out += [f"- **{v}**" for v in verdict_lines(doc)]
    out += [f"- {line}" for line in _head(doc)] + [""]
    out.append("| stage | input | frames | " + " | ".join(f"{f} ms" for f in FIGURES) + " |")
    out.append("|---|---|---:|" + "---:|" * len(FIGURES))
    for title, lines in blocks(doc):
        for j, cells in enumerate(lines):
            name = cells[0].strip()
            out.append(f"| {title if j == 0 else ''} | {'*' + name + '*' if name == 'change' else '`' + name + '`'} | "
                       + " | ".join(cells[1:]) + " |")
    out += [""] + _skipped(doc) + ["", f"<sub>{LEGEND}. {method_line(doc)}.</sub>"]
    return "\n".join(out) + "\n"
