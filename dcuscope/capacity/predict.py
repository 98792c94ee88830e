"""Capacity predicted from the runs at 1 and 2 streams.

The model. Each streaming thread of the pipeline (the stages that push their output on it share
its time: :attr:`.measure.CountFigures.threads`) is busy a fraction u(n) of the run at n streams:
its stages' utilization summed. With the mux's batch the stream count, a thread serves one batch
per frame period, and a batch's service grows with its size; with a fixed batch, it serves more
batches. Either way u(n) grows about linearly in n, and so does the CPU the process uses (the
decoders, one per stream, are not stages but cost CPU). From n = 1 and 2:

    u(n) = u(1) + (n - 1) (u(2) - u(1))        for every thread, and likewise cpu(n)

The first thread to reach u(n) >= 1 saturates: it cannot keep up, frames queue or the sources
slow down. The machine saturates when cpu(n) reaches its cores. Below the first of the two, every
delay figure (e2e mean = A, p50, p95, p99, each stage's mean) is extrapolated the same way, and
the bounds are checked on the extrapolations; the predicted capacity is the largest count below
saturation whose predicted figures hold.

Where it fails. Threads share cores: when the threads' sum of utilization nears the cores, the
services themselves grow (time-sharing), which two light runs do not see; so does a shared
accelerator (one GPU for several inference stages), and caches that a larger batch overflows.
Queues near saturation grow faster than linearly (a thread at 90 % waits much more than at 45 %):
the percentiles predicted near the capacity are optimistic. The measured run says which.
"""

from __future__ import annotations

import os

from dcuscope.capacity.verdict import Slo

PREDICT_UP_TO = 64
"""The highest count the prediction looks at."""


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def thread_loads(figures: dict) -> dict[str, float]:
    """Thread (named by its stages, ``mux+infer``) -> its utilization: its stages' summed."""
    groups: dict[object, list[str]] = {}
    for stage, st in figures["stages"].items():
        if st["utilization"] is None:
            continue
        groups.setdefault(figures["threads"].get(stage, stage), []).append(stage)
    return {"+".join(stages): sum(figures["stages"][s]["utilization"] for s in stages) for stages in groups.values()}


def _line(one: float, two: float, n: int) -> float:
    return one + (n - 1) * (two - one)


def _figure(figures: dict, slo: Slo) -> float | None:
    if slo.stage == "e2e":
        est = figures["e2e"].get(slo.figure)
        return est["value"] if est else None
    st = figures["stages"].get(slo.stage)
    if st is None or slo.figure != "mean":
        return None
    return st.get(slo.kind)


def predict(one: dict, two: dict, slos: list[Slo], n_cores: int | None = None) -> dict:
    """The prediction from the count documents of 1 and 2 streams (:func:`.search.run_count`).

    ``{capacity, saturates_at, saturates, limit, a_ms: {n: ms}, fps_per_stream: {n: fps}, threads:
    {thread: {n: u}}, cpu_cores: {n: cores}, unpredicted: [bounds the model cannot extrapolate]}``.
    """
    n_cores = n_cores or cores()
    f1, f2 = one["figures"], two["figures"]
    loads1, loads2 = thread_loads(f1), thread_loads(f2)
    threads = {t: (loads1[t], loads2[t]) for t in loads1 if t in loads2}
    cpu = (one["cpu_cores"], two["cpu_cores"]) if one.get("cpu_cores") and two.get("cpu_cores") else None
    saturates_at, saturates = None, None
    for n in range(1, PREDICT_UP_TO + 1):
        over = {t: _line(*u, n) for t, u in threads.items() if _line(*u, n) >= 1.0}
        if over:
            worst = max(over, key=over.get)
            saturates_at, saturates = n, {"what": worst, "utilization": over[worst], "kind": "thread"}
            break
        if cpu and _line(*cpu, n) >= n_cores:
            saturates_at, saturates = n, {"what": f"the CPU ({n_cores} cores)", "utilization": _line(*cpu, n) / n_cores,
                                          "kind": "cpu"}
            break
    top = (saturates_at - 1) if saturates_at else PREDICT_UP_TO
    unpredicted = [s.text for s in slos if _figure(f1, s) is None or _figure(f2, s) is None]
    capacity, limit = top, saturates
    a_ms, fps = {}, {}
    rate = one.get("rate_fps")
    horizon = range(1, (saturates_at or PREDICT_UP_TO) + 1)
    for n in horizon:
        if f1["e2e"] and f2["e2e"] and n <= top:
            a_ms[n] = _line(f1["e2e"]["mean"]["value"], f2["e2e"]["mean"]["value"], n)
        if rate:  # a thread asked for more than its time delivers that much less
            fps[n] = rate / max([_line(*u, n) for u in threads.values()] + [1.0])
        broken = [s for s in slos if s.text not in unpredicted and not _holds(s, _line(_figure(f1, s), _figure(f2, s), n))]
        if broken and capacity == top and n <= top:
            capacity, limit = n - 1, {"what": broken[0].short(), "kind": "bound",
                                      "value_ms": _line(_figure(f1, broken[0]), _figure(f2, broken[0]), n), "at": n}
    return {"capacity": capacity, "saturates_at": saturates_at, "saturates": saturates, "limit": limit,
            "a_ms": a_ms, "fps_per_stream": fps,
            "threads": {t: {n: _line(*u, n) for n in horizon} for t, u in threads.items()},
            "cpu_cores": {n: _line(*cpu, n) for n in horizon} if cpu else {},
            "n_cores": n_cores, "unpredicted": unpredicted}


def _holds(slo: Slo, value: float) -> bool:
    return {"<=": value <= slo.value_ms, "<": value < slo.value_ms,
            ">=": value >= slo.value_ms, ">": value > slo.value_ms}[slo.op]


def describe(p: dict) -> str:
    """One line: ``predicted capacity 5: infer's thread saturates at 6 (utilization 104 %)``."""
    text = f"predicted capacity {p['capacity']}"
    limit = p["limit"]
    if limit is None:
        return text + f" or more: nothing saturates up to {PREDICT_UP_TO} streams"
    if limit["kind"] == "bound":
        return text + f": {limit['what']} predicted {limit['value_ms']:.0f} ms at {limit['at']}"
    what = f"thread {limit['what']}" if limit["kind"] == "thread" else limit["what"]
    return text + f": {what} saturates at {p['saturates_at']} (utilization {limit['utilization']:.0%})"
