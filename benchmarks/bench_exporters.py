"""Exporters benchmark: relay ingest and UI lag with /metrics scraped and OTLP export on, vs both off.

bench_relay.py's two phases (throughput: events/s into SQLite and the live view; lag: a /ui
Socket.IO client at the paper's rate, 4,300 events/s a node) at each node count, each run
on a fresh relay in two arms (and, with ``--arms ambo``, m and o: one exporter each):

- a: exporters off: no scraper, no ``--otlp``;
- b: a real Prometheus (``/usr/bin/prometheus``, loopback, a temporary storage folder)
  scraping the relay's ``/metrics`` every second, and ``--otlp`` to a loopback OTLP/HTTP sink
  in this process (answers 200 to ``POST /v1/traces``, decodes each request with
  ``opentelemetry-proto`` to count its spans), ``--otlp-every`` at its default.

Prometheus is started before the relay, on the port the relay is then given, and each phase's
exporters' window opens once it has scraped the relay (in the lag phase, also once the relay has
finalised frames, what the exporters export) and closes once it has scraped it again (at once in
a window of several seconds): a short window on a busy machine still holds a scrape.
``--quick`` (a smoke test: 2 nodes, 400,000 events, a 1 s lag window, one round) runs both
phases of arm b on one Prometheus (the relay of each phase on the same port), started as arm a
begins its lag phase, so that nothing waits for a Prometheus' first scrape (~5 s: its target
discovery hands over new targets at most every 5 s): it scrapes a port nothing listens on yet
through arm a's lag phase.

Every arm gets the same ``--frame-limit``: the simulated nodes' frame delay quantile that
leaves ``--over-limit`` of the frames over it (default 5 %, more than a healthy pipeline has,
so the exporter gets more frames than it would in service), so arm b exports 1 in N frames
plus every frame over the limit. The arms run interleaved (a b, then b a: ``--repeat`` rounds)
on this shared, noisy machine, and the summary compares medians: ingest lost to the exporters
= 1 - rate_b / rate_a (goal <= 5 %; also per CPU-second of the relay), lag b vs a, relay CPU,
Prometheus' scrape duration and CPU, /metrics size (bytes, series), OTLP spans/s exported and
frames dropped. Prints one JSON line per node count, then two Markdown tables (b vs a, and
every arm against a). A figure a run could not produce is ``n/a (reason)`` in the JSON, and
``n/a [k]`` in a table with its reason under it (benchmarks/figures.py). Without Prometheus,
or when a relay or Prometheus does not start, it says so in one line and exits with status 2.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_exporters.py [--nodes 2 8] [--arms ab]
        [--events 12000000] [--seconds 12] [--repeat 2] [--over-limit 0.05] [--quick]
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import socket
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
from opentelemetry.proto.collector.trace.v1.trace_service_pb2 import (
    ExportTraceServiceRequest, ExportTraceServiceResponse,
)
from prometheus_client.parser import text_string_to_metric_families

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_relay import (  # noqa: E402
    EVENTS_PER_FRAME, SOURCES, Relay, _proc_cpu, measure_lag, measure_throughput,
)
from benchmarks.figures import NA, CannotRun, Notes, dumps, known, last_line, median, ratio, run  # noqa: E402
from dcuscope.probes.ship.simnode import synth_events  # noqa: E402

PROMETHEUS = "/usr/bin/prometheus"
ARMS = {"a": (False, False), "b": (True, True), "m": (True, False), "o": (False, True)}
"""Arm -> (Prometheus scrapes /metrics every second, --otlp on): a and b are the benchmark's,
m and o (one exporter each) tell which of the two costs what."""
FINAL_KEYS = ("frames_complete", "otlp_sampled", "otlp_over_limit", "otlp_dropped", "spans_exported")
SCRAPE_JOB = "dcuscope"


class OtlpSink:
    """A loopback OTLP/HTTP traces receiver: answers 200 and counts requests, bytes and spans."""

    def __init__(self) -> None:
        self.requests = self.bytes = self.spans = 0
        self.traces: set[bytes] = set()
        self._lock = threading.Lock()
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self._server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self._server.server_port}/v1/traces"
        # polled every 50 ms, not 500: stop() returns as soon (the arm b rigs stop one after another)
        threading.Thread(target=self._server.serve_forever, args=(0.05,), daemon=True).start()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        sink = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"  # keep-alive, as the exporter's session expects

            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                raw = gzip.decompress(body) if self.headers.get("Content-Encoding") == "gzip" else body
                request = ExportTraceServiceRequest.FromString(raw)
                spans = [span for rs in request.resource_spans for ss in rs.scope_spans for span in ss.spans]
                with sink._lock:
                    sink.requests += 1
                    sink.bytes += len(body)
                    sink.spans += len(spans)
                    sink.traces.update(span.trace_id for span in spans)
                reply = ExportTraceServiceResponse().SerializeToString()
                self.send_response(200 if self.path == "/v1/traces" else 404)
                self.send_header("Content-Type", "application/x-protobuf")
                self.send_header("Content-Length", str(len(reply)))
                self.end_headers()
                self.wfile.write(reply)

            def log_message(self, *args) -> None:  # one line a request would flood the benchmark's output
                pass

        return Handler

    def counts(self) -> dict:
        with self._lock:
            return {"requests": self.requests, "bytes": self.bytes, "spans": self.spans, "traces": len(self.traces)}

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Prometheus:
    """A real Prometheus scraping ``target`` (the relay's base URL, or where it will listen) every second."""

    def __init__(self, target: str, folder: Path) -> None:
        folder.mkdir(parents=True)
        host = urllib.parse.urlsplit(target).netloc
        self.port = int(host.rsplit(":", 1)[1])
        config = folder / "prometheus.yml"
        config.write_text(f"global: {{scrape_interval: 1s, scrape_timeout: 1s}}\n"
                          f"scrape_configs:\n  - job_name: {SCRAPE_JOB}\n"
                          f"    static_configs: [{{targets: ['{host}']}}]\n")
        self.url = f"http://127.0.0.1:{_free_port()}"
        self.log = folder / "prometheus.log"
        with self.log.open("wb") as log:
            self.proc = subprocess.Popen(
                [PROMETHEUS, f"--config.file={config}", f"--storage.tsdb.path={folder / 'data'}",
                 f"--web.listen-address={self.url.removeprefix('http://')}", "--log.level=warn"],
                stdout=log, stderr=log)
        self.scraping = False

    def wait_for_first_scrape(self, timeout_s: float = 60.0) -> None:
        """Until it has scraped the target once, successfully: ~5 s after it starts (its discovery
        manager hands over new targets at most every 5 s)."""
        deadline = time.monotonic() + timeout_s
        while not self.scraping and time.monotonic() < deadline:
            self._alive()
            try:
                self.scraping = self.last_scrape() is not None
            except OSError:
                pass  # not listening yet
            time.sleep(0.0 if self.scraping else 0.1)
        if self.scraping:
            return
        raise CannotRun(f"prometheus did not scrape the relay within {timeout_s:g} s")

    def wait_for_scrape_after(self, since: float, timeout_s: float = 30.0) -> bool:
        """Until it has scraped the target successfully after ``since`` (CLOCK_REALTIME, s): at
        once when a window of several scrape intervals closes, up to a scrape interval when a short
        one does, longer when this machine is busy. False if none came within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._alive()
            last = self.last_scrape()
            if last is not None and last > since:
                return True
            time.sleep(0.05)
        return False

    def last_scrape(self) -> float | None:
        """When (CLOCK_REALTIME, s) its last scrape of the target began, if that scrape succeeded."""
        result = self.query(f'timestamp(up{{job="{SCRAPE_JOB}"}} == 1)')
        return float(result[0]["value"][1]) if result else None

    def _alive(self) -> None:
        if self.proc.poll() is not None:
            raise CannotRun(f"prometheus exited (status {self.proc.returncode}): "
                            f"{last_line(self.log.read_text(errors='replace'))}")

    def query(self, promql: str, at: float | None = None) -> list[dict]:
        params = {"query": promql} | ({"time": f"{at:.3f}"} if at else {})
        with urllib.request.urlopen(f"{self.url}/api/v1/query?{urllib.parse.urlencode(params)}", timeout=10) as r:
            return json.loads(r.read())["data"]["result"]

    def value(self, promql: str, at: float) -> float | None:
        result = self.query(promql, at)
        return float(result[0]["value"][1]) if result else None

    def scrapes(self, since: float, until: float) -> dict:
        """Its scrapes of the relay between two CLOCK_REALTIME instants (s)."""
        span = f"[{max(1, math.ceil(until - since))}s]"
        job = f'{{job="{SCRAPE_JOB}"}}'
        total = self.value(f"count_over_time(up{job}{span})", until) or 0
        ok = self.value(f"sum_over_time(up{job}{span})", until) or 0
        none = f"Prometheus recorded no scrape of the relay in the {span} window"
        mean = known(self.value(f"avg_over_time(scrape_duration_seconds{job}{span})", until), none)
        worst = known(self.value(f"max_over_time(scrape_duration_seconds{job}{span})", until), none)
        return {"scrapes": int(total), "scrapes_ok": int(ok),
                "scrape_ms_mean": round(1000 * mean, 1), "scrape_ms_max": round(1000 * worst, 1)}

    def cpu_s(self) -> float:
        return _proc_cpu(self.proc.pid)

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)


def read_metrics(url: str) -> dict:
    """One GET of ``url``/metrics: its size, series, and the exporters' counters."""
    started = time.monotonic()
    with urllib.request.urlopen(url + "/metrics", timeout=30) as r:
        body = r.read()
    get_ms = 1000 * (time.monotonic() - started)
    text = body.decode()
    samples = [s for family in text_string_to_metric_families(text) for s in family.samples]

    def total(name: str, **labels: str) -> float:
        return sum(s.value for s in samples if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()))

    return {"bytes": len(body), "get_ms": round(get_ms, 1),
            # one exposition line is one series Prometheus stores (the _created ones included)
            "series": sum(1 for line in text.splitlines() if line and not line.startswith("#")),
            "series_dcu1": sum(1 for s in samples if s.labels.get("node") == "DCU-1"),
            "frames_complete": total("dcuscope_frames_complete_total"),
            "otlp_sampled": total("dcuscope_otlp_frames_total", why="sampled"),
            "otlp_over_limit": total("dcuscope_otlp_frames_total", why="over_limit"),
            "otlp_dropped": total("dcuscope_otlp_frames_dropped_total"),
            "spans_exported": total("dcuscope_otlp_spans_exported_total"),
            "otlp_queue": total("dcuscope_otlp_queue_frames")}


def frame_limit_ms(over: float, frames: int = 20_000) -> float:
    """The frame delay (origin to sink) of the simulated nodes that ``over`` of their frames exceed."""
    ev = synth_events(frames, SOURCES, 100.0, 0, seed=1)
    key = (ev["source"].astype(np.int64) << 32) + ev["frame"]
    order = np.argsort(key, kind="stable")
    key, ts = key[order], ev["ts"][order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    delay = np.maximum.reduceat(ts, starts) - np.minimum.reduceat(ts, starts)
    return float(np.quantile(delay, 1 - over)) / 1e6


def start_prometheus(folder: Path) -> Prometheus:
    """A Prometheus scraping a free port of loopback, where a relay is to listen."""
    return Prometheus(f"http://127.0.0.1:{_free_port()}", folder)


class Rig:
    """One fresh relay; as its arm says, an OTLP sink it exports to and a Prometheus scraping it
    (``prom``: one already scraping the port the relay is to listen on, left running at stop();
    else one of the rig's own, started before the relay)."""

    def __init__(self, arm: str, folder: Path, limit_ms: float, prom: Prometheus | None = None) -> None:
        folder.mkdir(parents=True)
        scrape, otlp = ARMS[arm]
        self.sink = OtlpSink() if otlp else None
        self.relay = self.prom = None
        self.own_prom = scrape and prom is None
        self.exporting = scrape or otlp
        self.sink_final: dict = {}
        args = ["--frame-limit", f"{limit_ms:.3f}"] + (["--otlp", self.sink.url] if self.sink else [])
        try:
            if scrape:
                # Started first: its target discovery (~5 s) goes on while the relay starts.
                self.prom = start_prometheus(folder / "prometheus") if prom is None else prom
                args += ["--port", str(self.prom.port)]  # after Relay's own --port 0: the last one counts
            self.relay = Relay(folder / "relay.db", args)
        except BaseException:
            self.stop()
            raise

    def mark(self, since: dict | None = None) -> dict:
        """The exporters' counters now, once Prometheus (if any) scrapes the relay (after ``since``,
        the mark that opened the window this one closes: so that the window holds a scrape)."""
        if self.prom:
            self.prom.wait_for_first_scrape()
            if since is not None:
                self.prom.wait_for_scrape_after(since["t"])
        return {"t": time.time(), "prom_cpu": self.prom.cpu_s() if self.prom else 0.0,
                "sink": self.sink.counts() if self.sink else {"spans": 0, "traces": 0},
                "metrics": read_metrics(self.relay.url)}

    def wait_for_finalised_frames(self, timeout_s: float = 30.0) -> None:
        """Until the relay has finalised a frame (the frames the exporters export), or ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while read_metrics(self.relay.url)["frames_complete"] == 0 and time.monotonic() < deadline:
            time.sleep(0.1)

    def between(self, start: dict, end: dict) -> dict:
        """The exporters' figures over a window opened by ``start`` and closed by ``end`` (marks)."""
        wall = end["t"] - start["t"]
        m0, m1 = start["metrics"], end["metrics"]

        def rate(key: str) -> float:
            return round((m1[key] - m0[key]) / wall, 1)

        complete = m1["frames_complete"] - m0["frames_complete"]
        scraped = {**self.prom.scrapes(start["t"], end["t"]),
                   "prometheus_cpu_pct": round(100 * (end["prom_cpu"] - start["prom_cpu"]) / wall)} if self.prom else {}
        return {**scraped,
                "metrics_bytes": m1["bytes"], "metrics_series": m1["series"], "series_dcu1": m1["series_dcu1"],
                "metrics_get_ms": m1["get_ms"], "frames_complete_per_s": rate("frames_complete"),
                "otlp_frames_per_s": round(rate("otlp_sampled") + rate("otlp_over_limit"), 1),
                "over_limit_share": round(ratio(m1["otlp_over_limit"] - m0["otlp_over_limit"], complete,
                                                "no frame completed in the window"), 4),
                "spans_exported_per_s": rate("spans_exported"),
                "sink_spans_per_s": round((end["sink"]["spans"] - start["sink"]["spans"]) / wall, 1),
                "sink_traces_per_s": round((end["sink"]["traces"] - start["sink"]["traces"]) / wall, 1),
                "otlp_frames_dropped": int(m1["otlp_dropped"] - m0["otlp_dropped"]),
                "otlp_queue_end": int(m1["otlp_queue"])}  # a backlog here is dropped in a longer run

    def stop(self) -> None:
        for part in (self.prom if self.own_prom else None, self.relay, self.sink):
            if part is not None:
                if part is self.sink:  # what reached it once the relay is gone
                    self.sink_final = self.sink.counts()
                part.stop()


def run_throughput(arm: str, n: int, args: argparse.Namespace, folder: Path, prom: Prometheus | None = None) -> dict:
    rig = Rig(arm, folder, args.frame_limit_ms, prom)
    try:
        start = rig.mark() if rig.exporting else None
        result = measure_throughput(rig.relay, n, args.events, args.batch_events)
        if rig.exporting:
            end = rig.mark(start)
            time.sleep(args.settle_s)  # the relay finalises frames ~2 s after they end: count their export too
            result["exporters"] = rig.between(start, end)
            final = rig.mark()["metrics"]
    finally:
        rig.stop()
    if rig.sink:
        sink = rig.sink_final
        result["exporters"]["final"] = {key: final[key] for key in FINAL_KEYS} | {
            "sink_spans": sink["spans"], "sink_traces": sink["traces"],
            "spans_per_trace": round(ratio(sink["spans"], sink["traces"], "the OTLP sink received no trace"), 2),
            "bytes_per_span": round(ratio(sink["bytes"], sink["spans"], "the OTLP sink received no span"), 1)}
    return result


def run_lag(arm: str, n: int, args: argparse.Namespace, folder: Path, prom: Prometheus | None = None) -> dict:
    rig = Rig(arm, folder, args.frame_limit_ms, prom)
    marks = {}

    def on_window(which: str) -> None:
        if which == "start":  # what the exporters export: frames finalised (~2 s of node time after they end)
            rig.wait_for_finalised_frames()
        marks[which] = rig.mark(marks.get("start"))

    try:
        result = measure_lag(rig.relay, n, args.rate, args.seconds, on_window if rig.exporting else None)
        if rig.exporting:
            result["exporters"] = rig.between(marks["start"], marks["end"])
        return result
    finally:
        rig.stop()


def _per_cpu(throughput: dict) -> float | NA:
    """Events stored per CPU-second of the relay in the 10-90 % window: less moved by other work
    on the machine than events/s, which fall when the relay gets less CPU."""
    cpu_s = throughput["relay_cpu_pct_in_window"] / 100
    return round(ratio(throughput["events_per_s"], cpu_s, "the relay used no CPU in the window"))


def per_arm(runs: list[dict], arm: str) -> dict:
    """Medians of one arm's runs, and per repetition its ingest rate (to pair with arm a's)."""
    mine = [r for r in runs if r["arm"] == arm]
    none = f"no run of arm {arm}"
    return {"ingest": median([r["throughput"]["events_per_s"] for r in mine], none),
            "ingest_per_cpu_s": median([_per_cpu(r["throughput"]) for r in mine], none),
            **{key: median([r["lag"][key] for r in mine], none)
               for key in ("lag_p50_ms", "lag_p99_ms", "relay_cpu_pct")},
            "by_rep": {r["rep"]: r["throughput"]["events_per_s"] for r in mine}}


def _lost(part: float | NA, whole: float | NA) -> float | NA:
    """The share of ``whole`` that ``part`` lacks: 1 - part / whole."""
    return round(1 - ratio(part, whole, "arm a stored no event"), 3)


def summarise(runs: list[dict]) -> dict:
    """Medians per arm and the ratios of each arm to arm a over the interleaved ``runs``."""
    def med(phase: str, key: str) -> float | NA:
        return median([r[phase].get("exporters", {}).get(key) for r in runs if r["arm"] == "b"],
                      f"no {key} measured in arm b")

    arms = {arm: per_arm(runs, arm) for arm in dict.fromkeys(r["arm"] for r in runs)}
    a_by_rep = per_arm(runs, "a")["by_rep"]
    for arm, figures in arms.items():
        by_rep = figures.pop("by_rep")
        if arm != "a":
            figures["ingest_lost"] = _lost(figures["ingest"], per_arm(runs, "a")["ingest"])
            figures["ingest_per_cpu_lost"] = _lost(figures["ingest_per_cpu_s"], per_arm(runs, "a")["ingest_per_cpu_s"])
            figures["ingest_lost_per_pair"] = [_lost(rate, a_by_rep.get(rep, NA(f"no run of arm a in round {rep + 1}")))
                                               for rep, rate in by_rep.items()]
    a, b = arms.get("a", {}), arms.get("b", {})

    def get(figures: dict, key: str, arm: str) -> float | NA:
        return figures.get(key, NA(f"no run of arm {arm}"))

    return {
        "ingest_a": get(a, "ingest", "a"), "ingest_b": get(b, "ingest", "b"), "ingest_lost": get(b, "ingest_lost", "b"),
        "ingest_lost_per_pair": b.get("ingest_lost_per_pair", []),
        "ingest_per_cpu_lost": get(b, "ingest_per_cpu_lost", "b"),
        **{f"{key}_{arm}": get(figures, key, arm) for key in ("lag_p50_ms", "lag_p99_ms", "relay_cpu_pct")
           for arm, figures in (("a", a), ("b", b))},
        **{key: med("lag", key) for key in (
            "scrape_ms_mean", "scrape_ms_max", "prometheus_cpu_pct", "metrics_bytes", "metrics_series",
            "series_dcu1", "spans_exported_per_s", "sink_spans_per_s", "otlp_frames_per_s", "over_limit_share",
            "otlp_frames_dropped")},
        "tp_scrape_ms_max": med("throughput", "scrape_ms_max"),
        "tp_otlp_frames_dropped": med("throughput", "otlp_frames_dropped"),
        "arms": arms,
    }


def _fmt(notes: Notes, v, unit: str = "") -> str:
    """``v`` shortened (12 k, 1.20 M) with ``unit``, or ``n/a [k]`` with its reason in ``notes``."""
    if isinstance(v, float) and abs(v) >= 1000 or isinstance(v, int) and abs(v) >= 10000:
        return f"{v / 1000:,.0f} k{unit}" if abs(v) < 1e6 else f"{v / 1e6:.2f} M{unit}"
    return notes.cell(v, "g", unit)


def _with_notes(rows: list[str], notes: Notes) -> str:
    """The table, then (after a blank line, which ends a Markdown table) the reasons of its n/a cells."""
    return "\n".join(rows + ([""] + notes.lines() if notes else []))


def table(lines: list[dict]) -> str:
    head = ("| nodes | ingest a / b (events/s) | lost to exporters (per pair) | lag p50 a / b | lag p99 a / b "
            "| relay CPU, lag phase a / b | scrape mean / max | Prometheus CPU | /metrics bytes / series "
            "| OTLP spans/s (sink) | frames over limit | OTLP frames dropped (lag / throughput) |")
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    notes = Notes()
    for line in lines:
        s = line["summary"]

        def f(key: str, unit: str = "") -> str:
            return _fmt(notes, s[key], unit)

        lost = notes.cell(100 * known(s["ingest_lost"], "not measured"), ".1f", " %")
        per_pair = ", ".join(notes.cell(100 * known(x, "not measured"), ".1f") for x in s["ingest_lost_per_pair"])
        share = notes.cell(100 * known(s["over_limit_share"], "not measured"), ".1f", " %")
        rows.append(
            f"| {line['nodes']} | {f('ingest_a')} / {f('ingest_b')} | {lost} ({per_pair}) "
            f"| {f('lag_p50_ms_a')} / {f('lag_p50_ms_b')} ms | {f('lag_p99_ms_a')} / {f('lag_p99_ms_b')} ms "
            f"| {f('relay_cpu_pct_a')} / {f('relay_cpu_pct_b')} % "
            f"| {f('scrape_ms_mean')} / {f('scrape_ms_max')} ms | {f('prometheus_cpu_pct')} % "
            f"| {f('metrics_bytes')} / {f('metrics_series')} "
            f"| {f('spans_exported_per_s')} ({f('sink_spans_per_s')}) | {share} "
            f"| {f('otlp_frames_dropped')} / {f('tp_otlp_frames_dropped')} |")
    return _with_notes(rows, notes)


def arms_table(lines: list[dict]) -> str:
    """Every arm's medians, ingest also per relay CPU-second, and what each lost against arm a."""
    rows = ["| nodes | arm | ingest, events/s (lost vs a) | per relay CPU-s (lost vs a) | lag p50 / p99 "
            "| relay CPU, lag phase |",
            "|---|---|---|---|---|---|"]
    notes = Notes()

    def lost(f: dict, key: str) -> str:  # arm a has no loss against itself
        return f" ({notes.cell(100 * known(f[key], 'not measured'), '.1f', ' %')})" if key in f else ""

    for line in lines:
        for arm, f in line["summary"]["arms"].items():
            rows.append(f"| {line['nodes']} | {arm} | {_fmt(notes, f['ingest'])}{lost(f, 'ingest_lost')} "
                        f"| {_fmt(notes, f['ingest_per_cpu_s'])}{lost(f, 'ingest_per_cpu_lost')} "
                        f"| {_fmt(notes, f['lag_p50_ms'])} / {_fmt(notes, f['lag_p99_ms'])} ms "
                        f"| {_fmt(notes, f['relay_cpu_pct'])} % |")
    return _with_notes(rows, notes)


def bench(n: int, args: argparse.Namespace, tmp: Path) -> dict:
    """Every run at ``n`` nodes: the arms in order, then reversed, ... (a b, b a, ...: against drift)."""
    runs = []
    load = round(os.getloadavg()[0], 1)
    order = [(rep, arm) for rep in range(args.repeat) for arm in (args.arms if rep % 2 == 0 else args.arms[::-1])]
    # --quick: one Prometheus per arm that scrapes, for both its phases (each phase's relay on its
    # port), started as the run before it begins its lag phase: its ~5 s to a first scrape pass
    # while that phase starts its relay and nodes and measures (it scrapes a port nothing listens
    # on yet, once a second), not before the arm's own throughput phase.
    proms: dict[tuple[int, str], Prometheus] = {}

    def prometheus_for(k: int) -> None:
        rep, arm = order[k]
        if args.one_prometheus and ARMS[arm][0] and (rep, arm) not in proms:
            proms[rep, arm] = start_prometheus(tmp / f"n{n}-{rep}{arm}-prometheus")

    try:
        for k, (rep, arm) in enumerate(order):
            folder = tmp / f"n{n}-{rep}{arm}"
            prometheus_for(k)
            prom = proms.get((rep, arm))
            throughput = run_throughput(arm, n, args, folder / "throughput", prom)
            if k + 1 < len(order):
                prometheus_for(k + 1)
            runs.append({"arm": arm, "rep": rep, "throughput": throughput,
                         "lag": run_lag(arm, n, args, folder / "lag", prom)})
            if prom is not None:
                proms.pop((rep, arm)).stop()
            shutil.rmtree(folder)  # a throughput run's database is ~0.5 GB
    finally:
        for prom in proms.values():
            prom.stop()
    return {"nodes": n, "cpus": os.cpu_count(), "load_before": load, "frame_limit_ms": round(args.frame_limit_ms, 2),
            "events_per_frame": EVENTS_PER_FRAME, "summary": summarise(runs), "runs": runs}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nodes", type=int, nargs="+", default=[2, 8])
    p.add_argument("--events", type=int, default=12_000_000,
                   help="events in all for a throughput run (enough for several scrapes in its window)")
    p.add_argument("--batch-events", type=int, default=8192, help="events per batch in the throughput phase")
    p.add_argument("--rate", type=float, default=4300.0, help="events/s per node in the lag phase (the paper's DCU)")
    p.add_argument("--seconds", type=float, default=12.0, help="length of the lag window")
    p.add_argument("--repeat", type=int, default=2, help="rounds of the arms (a b, then b a, ...) per node count")
    p.add_argument("--arms", default="ab", help="a: exporters off; b: both on; m: /metrics scraped only; o: OTLP only "
                                                "(default ab; e.g. ambo to tell the exporters' costs apart)")
    p.add_argument("--over-limit", type=float, default=0.05, help="share of frames over the --frame-limit given")
    p.add_argument("--settle", dest="settle_s", type=float, default=3.0,
                   help="seconds after a throughput run in arm b before its exporters' final counts")
    p.add_argument("--quick", action="store_true",
                   help="a smoke test: 2 nodes, 400,000 events, a 1 s lag window, one round, one Prometheus "
                        "for both phases of arm b, started during arm a's lag phase")
    args = p.parse_args(argv)
    args.one_prometheus = args.quick
    if args.quick:
        args.nodes, args.events, args.seconds, args.repeat, args.settle_s = [2], 400_000, 1.0, 1, 1.0
    if "a" not in args.arms or not set(args.arms) <= set(ARMS) or len(set(args.arms)) != len(args.arms):
        p.error(f"--arms {args.arms!r}: give a and any of {''.join(ARMS)[1:]}, each once")
    if not 0 < args.over_limit < 1:
        p.error(f"--over-limit must be between 0 and 1, not {args.over_limit}")
    if not Path(PROMETHEUS).exists() and set(args.arms) & {"b", "m"}:
        raise CannotRun(f"{PROMETHEUS} is missing: install Debian's prometheus (scripts/setup.sh does)")
    args.frame_limit_ms = frame_limit_ms(args.over_limit)
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.nodes:
            lines.append(bench(n, args, Path(tmp)))
            print(dumps(lines[-1]), flush=True)
    print(table(lines) + "\n", flush=True)
    print(arms_table(lines), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run(main))
