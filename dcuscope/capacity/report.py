"""The capacity report: a terminal table in the shape of the paper's Tables 4-6 (the delay per
stream count) with Figure 12's per-stage data, the prediction beside the measurement, and the
answer in one line; the same as Markdown, and the whole document as JSON."""

from __future__ import annotations

from dcuscope.capacity.predict import describe

E2E_FIGURES = ("mean", "p50", "p95", "p99")


def _est(e: dict | None, digits: int = 1) -> str:
    if not e:
        return "n/a"
    return f"{e['value']:.{digits}f} ({e['low']:.{digits}f}–{e['high']:.{digits}f})"


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.0%}"


def _ms(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


def limiting(neck: dict | None) -> str:
    """The limiting stage as ``infer 62%, thread 97% sat.`` (its thread's utilization where other stages share it)."""
    if not neck:
        return "n/a"
    if neck.get("utilization") is None:
        return f"{neck['stage']} (no service times)"
    thread = neck.get("thread_utilization")
    shared = f", thread {thread:.0%}" if thread is not None and thread >= neck["utilization"] + 0.005 else ""
    return f"{neck['stage']} {neck['utilization']:.0%}{shared}{' sat.' if neck.get('saturated') else ''}"


def _dropped(figs: dict) -> str:
    total = sum(figs["dropped"].values())
    if not total:
        return "0"
    return f"{total} (" + ", ".join(f"{k} {v}" for k, v in figs["dropped"].items()) + ")"


def _cpu(c: dict) -> str:
    cpu = "n/a" if c.get("cpu_cores") is None else f"{c['cpu_cores']:.2f}"
    if c.get("server_cores") is not None:
        cpu += f" + serve-rtsp {c['server_cores']:.2f}"
    return cpu


def count_rows(doc: dict) -> list[list[str]]:
    """Per count: streams, fps/stream, A, p50, p95, p99, limiting stage, dropped, CPU cores, outcome."""
    rows = []
    for c in doc["counts"]:
        f = c.get("figures")
        if not f:
            rows.append([str(c["streams"])] + ["n/a"] * 8 + [f"failed: {c['error']}"])
            continue
        fps = f"{f['fps']['value']:.1f} ({f['fps']['low']:.1f}–{f['fps']['high']:.1f})" if f["fps"] else "n/a"
        if f["fps"] and abs(f["fps_mean"] - f["fps"]["value"]) >= 0.05:
            fps += f", mean {f['fps_mean']:.1f}"
        rows.append([str(c["streams"]), fps] + [_est(f["e2e"].get(k)) for k in E2E_FIGURES]
                    + [limiting(c["limiting"]), _dropped(f), _cpu(c),
                       c["outcome"] + (f": {c['error']}" if c["error"] else "")])
    return rows


COUNT_HEAD = ["streams", "fps/stream (slowest)", "A = S/n, mean ms", "p50 ms", "p95 ms", "p99 ms", "limiting stage",
              "dropped", "CPU cores", "bounds"]
STAGE_HEAD = ["streams", "stage", "delay ms", "service ms", "wait ms", "utilization"]
BETWEEN = "(between stages)"
"""The row of the frame delay spent in no stage: the delays of a count's rows sum to its A."""


def stage_rows(doc: dict) -> tuple[list[str], list[list[str]]]:
    """Figure 12's data, a row per count and stage: its mean delay, its service and wait (delay =
    service + wait, ms) and its utilization; then the time between stages."""
    stages = list(dict.fromkeys(s for c in doc["counts"] if c.get("figures") for s in c["figures"]["stages"]))
    rows = []
    for c in doc["counts"]:
        f = c.get("figures")
        if not f:
            continue
        for s in stages:
            st = f["stages"].get(s)
            if st is not None:
                rows.append([str(c["streams"]), s, _ms(st["delay"]), _ms(st["service"]), _ms(st["wait"]),
                             _pct(st["utilization"])])
        rows.append([str(c["streams"]), BETWEEN, _ms(f["between_ms"]), "–", "–", "–"])
    return STAGE_HEAD, rows


def prediction_rows(doc: dict) -> list[list[str]]:
    """Per count: measured and predicted A and fps/stream, and the busiest thread's predicted utilization."""
    p = doc.get("prediction")
    if not p:
        return []
    measured = {c["streams"]: c for c in doc["counts"] if c.get("figures")}
    shown = max(doc["plan"].get("max_streams", 0), *measured) * 2  # the rows a reader compares, not 64
    top = max([*measured, min(p["saturates_at"] or p["capacity"] + 1, shown)])
    rows = []
    for n in range(1, top + 1):
        c = measured.get(n)
        a = c["figures"]["e2e"].get("mean") if c else None
        fps = c["figures"]["fps"] if c else None
        busiest = max((u.get(n, u.get(str(n))) or 0.0 for u in p["threads"].values()), default=None)
        pa, pf = p["a_ms"].get(n, p["a_ms"].get(str(n))), p["fps_per_stream"].get(n, p["fps_per_stream"].get(str(n)))
        rows.append([str(n), "–" if a is None else f"{a['value']:.1f}", "–" if pa is None else f"{pa:.1f}",
                     "–" if fps is None else f"{fps['value']:.1f}", "–" if pf is None else f"{pf:.1f}",
                     "–" if c is None or not c["limiting"] else _pct(c["limiting"].get("thread_utilization")),
                     "–" if busiest is None else _pct(busiest)])
    return rows


PREDICTION_HEAD = ["streams", "A measured", "A predicted", "fps measured", "fps predicted", "busiest thread measured",
                   "busiest thread predicted"]


PLACEHOLDERS = ("–", "n/a")
"""What a cell of figures holds where it has none."""


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    # A column of figures is right-aligned whole, its "–" and "n/a" too; the first (streams) reads as a label.
    numeric = [i > 0 and all(r[i][:1].isdigit() or r[i] in PLACEHOLDERS for r in rows) for i in range(len(head))]
    fmt = lambda r: "  ".join(x.rjust(w) if numeric[i] else x.ljust(w)  # noqa: E731
                              for i, (x, w) in enumerate(zip(r, widths))).rstrip()
    return [fmt(head)] + [fmt(r) for r in rows]


def _markdown(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


def render(doc: dict, markdown: bool = False) -> str:
    table = _markdown if markdown else _table
    out = []
    h = doc["plan"]
    title = (f"dcuscope capacity {h['config']}: {h['duration_s']:g} s per count, first {h['warmup_s']:g} s left out; "
             f"bounds: {', '.join(doc['bounds'])}")
    out += [f"### {title}" if markdown else title, ""]
    if doc["counts"]:
        out += ["Frame delay per stream count (95 % intervals in brackets):" if not markdown else
                "#### Frame delay per stream count (the paper's Tables 4–6), 95 % intervals in brackets", ""]
        out += table(COUNT_HEAD, count_rows(doc)) + [""]
        head, rows = stage_rows(doc)
        out += ["Per stage (Figure 12's data): mean delay in ms = service (its own work) + wait (queued,\n"
                "batching, blocked downstream); utilization: the share of the run it was busy:" if not markdown else
                "#### Per stage (Figure 12's data): mean delay = service + wait, and utilization", ""]
        out += table(head, rows) + [""]
    p = doc.get("prediction")
    if p:
        out += ["Prediction from 1 and 2 streams beside the measurement:" if not markdown else
                "#### Prediction from 1 and 2 streams beside the measurement", ""]
        out += table(PREDICTION_HEAD, prediction_rows(doc))
        if describe(p) != doc.get("answer"):  # --predict: the answer is the prediction, said once, last
            out += ["", describe(p)]
        if p["unpredicted"]:
            out.append(f"not predicted (the model extrapolates e2e figures and stage means only): {', '.join(p['unpredicted'])}")
        out.append("")
    for note in doc.get("notes", []):
        out.append(f"note: {note}")
    answer = doc.get("answer")
    if answer:
        out += [""] * (out[-1] != "") + [f"**{answer}**" if markdown else answer]
    return "\n".join(out).rstrip() + "\n"
