"""Exporters benchmark: relay ingest and UI lag with /metrics scraped and OTLP export on, vs both off.

bench_relay.py's two phases (throughput: events/s into SQLite and the live view; lag: a /ui
Socket.IO client at the paper's rate, 4,300 events/s a node) at each node count, each run
on a fresh relay in two arms:

- a: exporters off: no scraper, no ``--otlp``;
- b: a real Prometheus (``/usr/bin/prometheus``, loopback, a temporary storage folder)
  scraping the relay's ``/metrics`` every second, and ``--otlp`` to a loopback OTLP/HTTP sink
  in this process (answers 200 to ``POST /v1/traces``, decodes each request with
  ``opentelemetry-proto`` to count its spans), ``--otlp-every`` at its default.

Both arms get the same ``--frame-limit``: the simulated nodes' frame delay quantile that
leaves ``--over-limit`` of the frames over it (default 5 %, more than a healthy pipeline has,
so the exporter gets more frames than it would in service), so arm b exports 1 in N frames
plus every frame over the limit. The arms run interleaved a b b a (``--repeat`` pairs) on this
shared, noisy machine, and the summary compares medians: ingest lost to the exporters =
1 - rate_b / rate_a (goal <= 5 %), lag b vs a, relay CPU, Prometheus' scrape duration and
CPU, /metrics size (bytes, series), OTLP spans/s exported and frames dropped. Prints one JSON
line per node count, then a Markdown summary table.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_exporters.py [--nodes 2 8] [--events 12000000]
        [--seconds 12] [--repeat 2] [--over-limit 0.05] [--quick]
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import socket
import statistics
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

from benchmarks.bench_relay import (
    EVENTS_PER_FRAME, SOURCES, Relay, _proc_cpu, measure_lag, measure_throughput,
)
from probes.simnode import synth_events

PROMETHEUS = "/usr/bin/prometheus"
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
        threading.Thread(target=self._server.serve_forever, daemon=True).start()

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
                    sink.requests, sink.bytes, sink.spans = sink.requests + 1, sink.bytes + len(body), sink.spans + len(spans)
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
    """A real Prometheus scraping ``target`` (the relay's base URL) every second."""

    def __init__(self, target: str, folder: Path) -> None:
        folder.mkdir(parents=True)
        host = urllib.parse.urlsplit(target).netloc
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
        """Until it has scraped the target once: ~5 s after it starts (its discovery manager
        hands over new targets at most every 5 s)."""
        deadline = time.monotonic() + timeout_s
        while not self.scraping and time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"prometheus exited: {self.log.read_text()[-1000:]}")
            try:
                self.scraping = bool(self.query(f'up{{job="{SCRAPE_JOB}"}}'))
            except OSError:
                pass  # not listening yet
            time.sleep(0.0 if self.scraping else 0.1)
        if self.scraping:
            return
        raise RuntimeError("prometheus did not scrape the relay within a minute")

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
        mean = self.value(f"avg_over_time(scrape_duration_seconds{job}{span})", until)
        worst = self.value(f"max_over_time(scrape_duration_seconds{job}{span})", until)
        return {"scrapes": int(total), "scrapes_ok": int(ok),
                "scrape_ms_mean": round(1000 * mean, 1) if mean is not None else None,
                "scrape_ms_max": round(1000 * worst, 1) if worst is not None else None}

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
            "spans_exported": total("dcuscope_otlp_spans_exported_total")}


def frame_limit_ms(over: float, frames: int = 20_000) -> float:
    """The frame delay (origin to sink) of the simulated nodes that ``over`` of their frames exceed."""
    ev = synth_events(frames, SOURCES, 100.0, 0, seed=1)
    key = (ev["source"].astype(np.int64) << 32) + ev["frame"]
    order = np.argsort(key, kind="stable")
    key, ts = key[order], ev["ts"][order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    delay = np.maximum.reduceat(ts, starts) - np.minimum.reduceat(ts, starts)
    return float(np.quantile(delay, 1 - over)) / 1e6


class Rig:
    """One fresh relay; in arm b also its OTLP sink and a Prometheus scraping it."""

    def __init__(self, arm: str, folder: Path, limit_ms: float) -> None:
        folder.mkdir(parents=True)
        self.sink = OtlpSink() if arm == "b" else None
        self.relay = self.prom = None
        self.sink_final: dict = {}
        args = ["--frame-limit", f"{limit_ms:.3f}"] + (["--otlp", self.sink.url] if self.sink else [])
        try:
            self.relay = Relay(folder / "relay.db", args)
            self.prom = Prometheus(self.relay.url, folder / "prometheus") if arm == "b" else None
        except BaseException:
            self.stop()
            raise

    def mark(self) -> dict:
        """The exporters' counters now (arm b), once Prometheus scrapes the relay."""
        self.prom.wait_for_first_scrape()
        return {"t": time.time(), "prom_cpu": self.prom.cpu_s(), "sink": self.sink.counts(),
                "metrics": read_metrics(self.relay.url)}

    def between(self, start: dict, end: dict) -> dict:
        """Arm b's figures over a window opened by ``start`` and closed by ``end`` (marks)."""
        wall = end["t"] - start["t"]
        m0, m1 = start["metrics"], end["metrics"]

        def rate(key: str) -> float:
            return round((m1[key] - m0[key]) / wall, 1)

        complete = m1["frames_complete"] - m0["frames_complete"]
        return {**self.prom.scrapes(start["t"], end["t"]),
                "prometheus_cpu_pct": round(100 * (end["prom_cpu"] - start["prom_cpu"]) / wall),
                "metrics_bytes": m1["bytes"], "metrics_series": m1["series"], "series_dcu1": m1["series_dcu1"],
                "metrics_get_ms": m1["get_ms"], "frames_complete_per_s": rate("frames_complete"),
                "otlp_frames_per_s": round(rate("otlp_sampled") + rate("otlp_over_limit"), 1),
                "over_limit_share": round((m1["otlp_over_limit"] - m0["otlp_over_limit"]) / complete, 4)
                if complete else None,
                "spans_exported_per_s": rate("spans_exported"),
                "sink_spans_per_s": round((end["sink"]["spans"] - start["sink"]["spans"]) / wall, 1),
                "sink_traces_per_s": round((end["sink"]["traces"] - start["sink"]["traces"]) / wall, 1),
                "otlp_frames_dropped": int(m1["otlp_dropped"] - m0["otlp_dropped"])}

    def stop(self) -> None:
        for part in (self.prom, self.relay, self.sink):
            if part is not None:
                if part is self.sink:  # what reached it once the relay is gone
                    self.sink_final = self.sink.counts()
                part.stop()


def run_throughput(arm: str, n: int, args: argparse.Namespace, folder: Path) -> dict:
    rig = Rig(arm, folder, args.frame_limit_ms)
    try:
        start = rig.mark() if rig.prom else None
        result = measure_throughput(rig.relay, n, args.events, args.batch_events)
        if rig.prom:
            end = rig.mark()
            time.sleep(args.settle_s)  # the relay finalises frames ~2 s after they end: count their export too
            result["exporters"] = rig.between(start, end)
            final = rig.mark()["metrics"]
    finally:
        rig.stop()
    if rig.prom:
        sink = rig.sink_final
        result["exporters"]["final"] = {key: final[key] for key in FINAL_KEYS} | {
            "sink_spans": sink["spans"], "sink_traces": sink["traces"],
            "spans_per_trace": round(sink["spans"] / sink["traces"], 2) if sink["traces"] else None,
            "bytes_per_span": round(sink["bytes"] / sink["spans"], 1) if sink["spans"] else None}
    return result


def run_lag(arm: str, n: int, args: argparse.Namespace, folder: Path) -> dict:
    rig = Rig(arm, folder, args.frame_limit_ms)
    marks = {}
    try:
        on_window = (lambda which: marks.__setitem__(which, rig.mark())) if rig.prom else None
        result = measure_lag(rig.relay, n, args.rate, args.seconds, on_window)
        if rig.prom:
            result["exporters"] = rig.between(marks["start"], marks["end"])
        return result
    finally:
        rig.stop()


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return statistics.median(values) if values else None


def summarise(runs: list[dict]) -> dict:
    """Medians per arm and the ratios of b to a over the interleaved ``runs``."""
    def med(arm: str, phase: str, key: str, sub: str | None = None) -> float | None:
        return _median([(r[phase][sub] if sub else r[phase]).get(key) for r in runs if r["arm"] == arm])

    rate_a, rate_b = med("a", "throughput", "events_per_s"), med("b", "throughput", "events_per_s")
    pairs = {}
    for r in runs:
        pairs.setdefault(r["rep"], {})[r["arm"]] = r["throughput"]["events_per_s"]
    return {
        "ingest_a": rate_a, "ingest_b": rate_b,
        "ingest_lost": round(1 - rate_b / rate_a, 3) if rate_a and rate_b else None,
        "ingest_lost_per_pair": [round(1 - p["b"] / p["a"], 3) for p in pairs.values() if p.get("a") and p.get("b")],
        **{f"{key}_{arm}": med(arm, "lag", key) for key in ("lag_p50_ms", "lag_p99_ms", "relay_cpu_pct")
           for arm in "ab"},
        **{f"tp_relay_cpu_pct_{arm}": med(arm, "throughput", "relay_cpu_pct_in_window") for arm in "ab"},
        **{key: med("b", "lag", key, "exporters") for key in (
            "scrape_ms_mean", "scrape_ms_max", "prometheus_cpu_pct", "metrics_bytes", "metrics_series",
            "series_dcu1", "spans_exported_per_s", "sink_spans_per_s", "otlp_frames_per_s", "over_limit_share",
            "otlp_frames_dropped")},
        "tp_scrape_ms_max": med("b", "throughput", "scrape_ms_max", "exporters"),
        "tp_scrapes_failed": _median([r["throughput"]["exporters"]["scrapes"] - r["throughput"]["exporters"]["scrapes_ok"]
                                      for r in runs if r["arm"] == "b"]),
        "tp_otlp_frames_dropped": med("b", "throughput", "otlp_frames_dropped", "exporters"),
    }


def _fmt(v, unit: str = "") -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and abs(v) >= 1000 or isinstance(v, int) and abs(v) >= 10000:
        return f"{v / 1000:,.0f} k{unit}" if abs(v) < 1e6 else f"{v / 1e6:.2f} M{unit}"
    return f"{v:g}{unit}"


def table(lines: list[dict]) -> str:
    head = ("| nodes | ingest a / b (events/s) | lost to exporters (per pair) | lag p50 a / b | lag p99 a / b "
            "| relay CPU, lag phase a / b | scrape mean / max | Prometheus CPU | /metrics bytes / series "
            "| OTLP spans/s (sink) | frames over limit | OTLP frames dropped (lag / throughput) |")
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    for line in lines:
        s = line["summary"]
        lost = f"{100 * s['ingest_lost']:.1f} %" if s["ingest_lost"] is not None else "–"
        per_pair = ", ".join(f"{100 * x:.1f}" for x in s["ingest_lost_per_pair"])
        share = f"{100 * s['over_limit_share']:.1f} %" if s["over_limit_share"] is not None else "–"
        rows.append(
            f"| {line['nodes']} | {_fmt(s['ingest_a'])} / {_fmt(s['ingest_b'])} | {lost} ({per_pair}) "
            f"| {_fmt(s['lag_p50_ms_a'])} / {_fmt(s['lag_p50_ms_b'])} ms | {_fmt(s['lag_p99_ms_a'])} / {_fmt(s['lag_p99_ms_b'])} ms "
            f"| {_fmt(s['relay_cpu_pct_a'])} / {_fmt(s['relay_cpu_pct_b'])} % "
            f"| {_fmt(s['scrape_ms_mean'])} / {_fmt(s['scrape_ms_max'])} ms | {_fmt(s['prometheus_cpu_pct'])} % "
            f"| {_fmt(s['metrics_bytes'])} / {_fmt(s['metrics_series'])} "
            f"| {_fmt(s['spans_exported_per_s'])} ({_fmt(s['sink_spans_per_s'])}) | {share} "
            f"| {_fmt(s['otlp_frames_dropped'])} / {_fmt(s['tp_otlp_frames_dropped'])} |")
    return "\n".join(rows)


def bench(n: int, args: argparse.Namespace, tmp: Path) -> dict:
    """Every run at ``n`` nodes: a b, b a, a b, ... (each pair in turn reversed, against drift)."""
    runs = []
    load = round(os.getloadavg()[0], 1)
    for rep in range(args.repeat):
        for arm in ("ab" if rep % 2 == 0 else "ba"):
            folder = tmp / f"n{n}-{rep}{arm}"
            runs.append({"arm": arm, "rep": rep,
                         "throughput": run_throughput(arm, n, args, folder / "throughput"),
                         "lag": run_lag(arm, n, args, folder / "lag")})
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
    p.add_argument("--repeat", type=int, default=2, help="pairs of runs (a b, b a, ...) per node count")
    p.add_argument("--over-limit", type=float, default=0.05, help="share of frames over the --frame-limit given")
    p.add_argument("--settle", dest="settle_s", type=float, default=3.0,
                   help="seconds after a throughput run in arm b before its exporters' final counts")
    p.add_argument("--quick", action="store_true", help="a smoke test: 2 nodes, 600,000 events, a 1.5 s lag window, one pair")
    args = p.parse_args(argv)
    if args.quick:
        args.nodes, args.events, args.seconds, args.repeat, args.settle_s = [2], 600_000, 1.5, 1, 1.0
    if not 0 < args.over_limit < 1:
        p.error(f"--over-limit must be between 0 and 1, not {args.over_limit}")
    if not Path(PROMETHEUS).exists():
        p.error(f"{PROMETHEUS} is missing: install Debian's prometheus (scripts/setup.sh does)")
    args.frame_limit_ms = frame_limit_ms(args.over_limit)
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.nodes:
            lines.append(bench(n, args, Path(tmp)))
            print(json.dumps(lines[-1]), flush=True)
    print(table(lines), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
