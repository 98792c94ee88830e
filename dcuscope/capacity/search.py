"""The step-up search: 1, 2, 3, ... streams, each in its own process, until a count does not pass.

Step-up rather than bisection: every count below the capacity is run once, and the report wants
each of them (the paper's tables give the delay at every count); a bisection would spend its runs
above the capacity, where a saturated pipeline runs slowest and tells least. A count that is
undecided ends the search too: the counts above it would rest on it.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from urllib.parse import urlparse
from urllib.request import url2pathname
from typing import Callable

from dcuscope.capacity.measure import measure
from dcuscope.capacity.plan import check_replicable, source_rate
from dcuscope.capacity.verdict import FAILS, HOLDS, Slo, check_fps, check_slo, outcome
from dcuscope.core.errors import UsageError
from dcuscope.pipeline.config import PipelineConfig
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import ORIGIN

START_ALLOWANCE_S = 90.0
"""Time a count may take beyond its --duration (start-up, model load) before it is killed."""


@dataclass
class Plan:
    config_file: Path
    config: PipelineConfig
    max_streams: int
    slos: list[Slo]
    fps_floor: float
    """Fraction of the source's rate the slowest stream must keep."""
    duration: float
    warmup: float
    keep_batch: bool = False
    rtsp: bool = False
    rtsp_bitrate: int = 4000
    workdir: Path = Path(".")
    counts: list[int] = field(default_factory=list)
    """The counts to run, in order."""
    past_failure: bool = False
    """Run every count of ``counts`` (--all-streams, --predict), not only up to the first that does not pass."""


def run_count(plan: Plan, streams: int) -> dict:
    """One count: its process, its trace measured, its bounds checked; the count's document."""
    trace = plan.workdir / f"streams-{streams}.trace.jsonl"
    spec = {"config": str(plan.config_file), "streams": streams, "keep_batch": plan.keep_batch,
            "trace": str(trace), "duration": plan.duration}
    doc: dict = {"streams": streams, "error": None, "cpu_cores": None, "server_cores": None}
    started = time.monotonic()
    try:
        with _served(plan, streams) as server:
            if server is not None:
                rate = source_rate(plan.config)
                spec["rtsp_uris"] = server.uris
                spec["mux_timeout_us"] = int(1e6 / float(rate)) if rate else 33_333  # one frame period
            result = _child(spec, plan.workdir / f"streams-{streams}.json", plan.duration)
        doc["server_cores"] = server.cores if server is not None else None
    except RuntimeError as exc:  # serve-rtsp did not start
        result = {"error": str(exc)}
    doc["wall_s"] = time.monotonic() - started
    if result.get("bad_input"):
        raise UsageError(result["error"])
    if "error" in result:
        return {**doc, "outcome": FAILS, "error": result["error"], "checks": [], "figures": None, "limiting": None}
    if result["lost"]:
        doc["error"] = "; ".join(f"source {i} lost: {why}" for i, why in result["lost"].items())
    run = read_trace(trace)
    figures = measure(run, streams, plan.warmup)
    doc["cpu_cores"] = cpu_cores(result["cpu"], run, plan.warmup)
    forced = source_rate(plan.config)
    rate = figures.nominal_fps or (float(forced) if forced else None)
    checks = [check_fps(figures, plan.fps_floor, rate)] + [check_slo(s, figures) for s in plan.slos]
    if figures.frames < 2:
        doc["error"] = doc["error"] or "no frame went through the whole pipeline after the warm-up"
    doc.update(outcome=FAILS if doc["error"] else outcome(checks), checks=[asdict(c) for c in checks],
               figures=figures.to_json(), limiting=figures.limiting, rate_fps=rate)
    return doc


def _served(plan: Plan, streams: int):
    """``--rtsp``: the streams of this count served live (stream i plays file source i mod their number)."""
    if not plan.rtsp:
        return contextlib.nullcontext()
    from dcuscope.capacity.rtspserve import RtspServer

    sources = plan.config.sources
    files = [Path(url2pathname(urlparse(sources[i % len(sources)].location).path)) for i in range(streams)]
    return RtspServer(files, plan.rtsp_bitrate)


def cpu_cores(samples: list, trace, warmup_s: float) -> float | None:
    """CPU cores the count's process used from the end of the warm-up (the first frame's origin +
    ``warmup_s``, on the trace's realtime clock) to its end; over the whole run when the trace's
    clock is another or the measured part is under a second."""
    if len(samples) < 2:
        return None
    origins = trace.events["ts"][trace.events["point"] == ORIGIN]
    start = origins.min() / 1e9 + warmup_s if trace.header.clock == "realtime" and len(origins) else samples[0][0]
    kept = [s for s in samples if s[0] >= start]
    if len(kept) < 2 or kept[-1][0] - kept[0][0] < 1.0:
        kept = samples
    (w0, c0), (w1, c1) = kept[0], kept[-1]
    return (c1 - c0) / (w1 - w0) if w1 > w0 else None


def _child(spec: dict, spec_file: Path, duration: float) -> dict:
    spec_file.write_text(json.dumps(spec))
    # A session of its own: Ctrl-C reaches this process only, which stops the child itself.
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.capacity.count", str(spec_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "GST_DEBUG": os.environ.get("GST_DEBUG", "0")})
    try:
        out, err = proc.communicate(timeout=duration + START_ALLOWANCE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return {"error": f"the run did not end within {duration + START_ALLOWANCE_S:.0f} s (killed)"}
    except BaseException:  # Ctrl-C: stop the count, leave no pipeline behind
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        raise
    lines = out.strip().splitlines()
    try:
        result = json.loads(lines[-1])
    except (IndexError, ValueError):
        tail = " ".join(err.strip().splitlines()[-3:])
        return {"error": f"the run ended with status {proc.returncode}: {tail or 'no output'}"}
    if result.get("aborted"):
        result = {"error": result["aborted"]}
    return result


def search(plan: Plan, say: Callable[[str], None],
           on_count: Callable[[dict], None] = lambda _: None) -> tuple[list[dict], str | None]:
    """Run the plan's counts until one does not pass; (the counts' documents, why it stopped early).
    Ctrl-C (or SIGTERM: :class:`Stopped`), wherever it comes in a count, stops the search with the
    counts measured before it."""
    check_replicable(plan.config, plan.rtsp)
    counts: list[dict] = []
    for streams in plan.counts:
        try:
            say(f"{streams} stream{'s' if streams != 1 else ''}: running {plan.duration:g} s "
                f"({plan.warmup:g} s warm-up left out)")
            doc = run_count(plan, streams)
        except KeyboardInterrupt as exc:
            return counts, f"stopped by {_by(exc)} during {streams} stream{'s' if streams != 1 else ''}"
        counts.append(doc)
        try:
            on_count(doc)
        except KeyboardInterrupt as exc:
            return counts, f"stopped by {_by(exc)} after {streams} stream{'s' if streams != 1 else ''}"
        if doc["outcome"] != HOLDS and not plan.past_failure:
            break
    return counts, None


class Stopped(KeyboardInterrupt):
    """A stop asked by a signal other than Ctrl-C (SIGTERM: a service manager, a CI job's timeout)."""

    def __init__(self, by: str):
        super().__init__(by)
        self.by = by


def _by(exc: KeyboardInterrupt) -> str:
    return exc.by if isinstance(exc, Stopped) else "Ctrl-C"


@contextlib.contextmanager
def stop_on_signals():
    """SIGINT and SIGTERM stop the search as Ctrl-C does, whatever this process inherited: a job
    started in the background of a shell ignores SIGINT, and ``dcuscope run`` stops on both too."""
    def stop(signum, _frame):
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise Stopped(signal.Signals(signum).name)

    before = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
