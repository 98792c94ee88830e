"""``--plot``: the paper's Figure 12 for this pipeline: each stage's mean delay stacked per stream
count (the bar's height is A = S/n; the gaps between stages on top), and frames/s per stream on a
second axis against the floor; predicted A beside the measured bars. Drawn with matplotlib
(an extra: ``pip install 'dcuscope[plot]'``)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from dcuscope.core.errors import UsageError

FORMATS = (".png", ".svg", ".pdf")
BETWEEN = "between stages"


def check_plot(path: Path) -> None:
    """UsageError before anything runs when the plot cannot be drawn or written."""
    if path.suffix.lower() not in FORMATS:
        raise UsageError(f"--plot {path}: give a file ending in {', '.join(FORMATS)}")
    if not path.parent.resolve().is_dir():
        raise UsageError(f"--plot {path}: no such folder {path.parent}")
    if importlib.util.find_spec("matplotlib") is None:
        raise UsageError("--plot needs matplotlib: pip install 'dcuscope[plot]' (or pip install matplotlib)")


def draw(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt

    counts = [c for c in doc["counts"] if c.get("figures")]
    stages = list(dict.fromkeys(s for c in counts for s in c["figures"]["stages"]))
    x = [c["streams"] for c in counts]
    fig, ax = plt.subplots(figsize=(8, 4.8), layout="constrained")
    bottom = [0.0] * len(counts)
    palette = [plt.get_cmap("tab10")(i) for i in (0, 1, 2, 4, 5, 6, 7, 8, 9)]  # no red: red is frames/s
    for i, stage in enumerate(stages + [BETWEEN]):
        heights = [max(0.0, (c["figures"]["between_ms"] or 0.0) if stage == BETWEEN
                       else (c["figures"]["stages"].get(stage, {}).get("delay") or 0.0)) for c in counts]
        ax.bar(x, heights, bottom=bottom, width=0.6, label=stage,
               color="lightgrey" if stage == BETWEEN else palette[i % len(palette)], edgecolor="white", linewidth=0.5)
        bottom = [b + h for b, h in zip(bottom, heights)]
    p99 = [(c["streams"], c["figures"]["e2e"]["p99"]) for c in counts if c["figures"]["e2e"].get("p99")]
    if p99:
        ax.errorbar([n for n, _ in p99], [e["value"] for _, e in p99],
                    yerr=[[e["value"] - e["low"] for _, e in p99], [e["high"] - e["value"] for _, e in p99]],
                    fmt="_", color="black", capsize=3, markersize=12, label="e2e p99 (95 % interval)")
    pred = (doc.get("prediction") or {}).get("a_ms") or {}
    if pred:
        ns = sorted(int(n) for n in pred)
        ax.plot(ns, [pred.get(n, pred.get(str(n))) for n in ns], "k--", marker="o", markersize=3, linewidth=1,
                label="A predicted from 1 and 2 streams")
    for slo in doc.get("slos", []):
        if slo["stage"] == "e2e" and slo["figure"] in ("p99", "mean"):
            ax.axhline(slo["value_ms"], color="black", linestyle="--" if slo["figure"] == "p99" else ":", linewidth=1,
                       label=f"bound e2e.{slo['figure']} {slo['op']} {slo['value_ms']:g} ms")
    ax.set_xlabel("streams")
    ax.set_ylabel("mean frame delay per stage, ms (stacked: A = S/n)")
    ax.set_xticks(sorted(set(x) | {int(n) for n in pred}))
    fps_ax = ax.twinx()
    fps = [(c["streams"], c["figures"]["fps"]) for c in counts if c["figures"]["fps"]]
    if fps:
        fps_ax.errorbar([n for n, _ in fps], [e["value"] for _, e in fps],
                        yerr=[[e["value"] - e["low"] for _, e in fps], [e["high"] - e["value"] for _, e in fps]],
                        color="tab:red", marker="s", markersize=4, linewidth=1.5, label="frames/s per stream (slowest)")
    rate = next((c.get("rate_fps") for c in counts if c.get("rate_fps")), None)
    if rate:
        floor = rate * doc["plan"]["fps_floor_pct"] / 100
        fps_ax.axhline(floor, color="tab:red", linestyle=":", linewidth=1,
                       label=f"floor {doc['plan']['fps_floor_pct']:g} % of {rate:g} fps")
    fps_ax.set_ylim(0, max([rate or 0.0] + [e["high"] for _, e in fps]) * 1.15 or 1.0)
    fps_ax.set_ylabel("frames/s per stream", color="tab:red")
    handles, labels = ax.get_legend_handles_labels()
    h2, l2 = fps_ax.get_legend_handles_labels()
    ax.legend(handles + h2, labels + l2, loc="upper left", fontsize=8, framealpha=0.9)
    title = f"dcuscope capacity: {Path(doc['plan']['config']).name}"
    if doc.get("answer"):
        title += f" — capacity {doc['capacity'] if doc.get('capacity') is not None else 'unknown'}"
    ax.set_title(title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
