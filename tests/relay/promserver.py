"""A real Prometheus server for tests: Debian's ``/usr/bin/prometheus`` on 127.0.0.1, scraping one
relay every second with the bearer token in a credentials file, evaluating rule files every
second, storing in the test's folder; helpers for its HTTP API (instant queries and alerts).

Debian's ``prometheus`` package is installed by ``make setup`` (scripts/setup.sh), like linuxptp
for tests/ptpnet.py: where it is missing the test fails saying so, it does not skip.
"""

from __future__ import annotations

import json
import signal
import subprocess
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
import yaml

from tests.ports import free_port
from tests.relay.helpers import wait_for

BIN = Path("/usr/bin")
"""Where Debian's prometheus package puts ``prometheus`` and ``promtool``."""
START_TIMEOUT_S = 60.0
JOB = "dcuscope-relay"


def require_tool(name: str) -> str:
    """The path of Prometheus' ``name`` (prometheus, promtool); fails the test where it is missing."""
    path = BIN / name
    if not path.exists():
        pytest.fail(f"{path} not found: run `make setup` (scripts/setup.sh installs Debian's prometheus package)")
    return str(path)


def scrape_config(target: str, folder: Path, token: str | None, rule_files: list[Path], every_s: float,
                  extra_jobs: list[dict] = (), tls_ca: Path | None = None) -> dict:
    """A Prometheus configuration scraping ``target`` (host:port) as job ``dcuscope-relay``, and ``extra_jobs``;
    over HTTPS, verifying the relay's certificate against ``tls_ca``, where given."""
    every = f"{round(every_s * 1000)}ms"  # Prometheus' durations take no fractions
    job = {"job_name": JOB, "scrape_interval": every, "scrape_timeout": every,
           "static_configs": [{"targets": [target]}]}
    if tls_ca is not None:
        job.update(scheme="https", tls_config={"ca_file": str(tls_ca)})
    if token is not None:
        credentials = folder / "relay.token"
        credentials.write_text(token)
        credentials.chmod(0o600)
        job["authorization"] = {"type": "Bearer", "credentials_file": str(credentials)}
    return {"global": {"scrape_interval": every, "evaluation_interval": every},
            "rule_files": [str(p) for p in rule_files], "scrape_configs": [job, *extra_jobs]}


class PromServer:
    """``prometheus`` in a subprocess, ready (``/-/ready``) once constructed; :meth:`stop` ends it."""

    def __init__(self, folder: Path, target: str, token: str | None = None, rule_files: list[Path] = (),
                 every_s: float = 1.0, extra_jobs: list[dict] = (), tls_ca: Path | None = None) -> None:
        binary = require_tool("prometheus")
        folder.mkdir(parents=True, exist_ok=True)
        self.config = folder / "prometheus.yml"
        self.config.write_text(yaml.safe_dump(scrape_config(target, folder, token, list(rule_files), every_s, list(extra_jobs),
                                                                   tls_ca)))
        self.log = folder / "prometheus.log"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        with open(self.log, "wb") as log:
            self.proc = subprocess.Popen(
                [binary, f"--config.file={self.config}", f"--storage.tsdb.path={folder / 'data'}",
                 f"--web.listen-address=127.0.0.1:{self.port}", "--log.level=warn"],
                stdout=log, stderr=subprocess.STDOUT, cwd=folder)
        try:
            wait_for(self._ready, START_TIMEOUT_S, 0.2, "prometheus to be ready")
        except BaseException:
            self.stop()
            raise

    def _ready(self) -> bool:
        if self.proc.poll() is not None:
            raise AssertionError(f"prometheus exited {self.proc.returncode}: {self.log.read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(f"{self.url}/-/ready", timeout=2) as r:
                return r.status == 200
        except OSError:
            return False

    def api(self, path: str, **params) -> dict | list:
        """``GET /api/v1/PATH?params``'s ``data``; AssertionError with Prometheus' error otherwise."""
        url = f"{self.url}/api/v1/{path}" + (f"?{urllib.parse.urlencode(params)}" if params else "")
        try:
            with urllib.request.urlopen(url, timeout=10) as r:
                body = json.loads(r.read())
        except urllib.error.HTTPError as exc:
            body = json.loads(exc.read())
        assert body.get("status") == "success", f"{url}: {body}"
        return body["data"]

    def query(self, expr: str) -> list[dict]:
        """An instant query's vector: ``[{"metric": {...}, "value": [t, "v"]}, ...]``."""
        data = self.api("query", query=expr)
        assert data["resultType"] == "vector", data
        return data["result"]

    def values(self, expr: str, label: str) -> dict[str, float]:
        """An instant query's values keyed by one label (``node``, ``stage``)."""
        return {s["metric"].get(label, ""): float(s["value"][1]) for s in self.query(expr)}

    def alerts(self, name: str | None = None) -> list[dict]:
        """``/api/v1/alerts``' alerts (each with ``labels``, ``state``: pending or firing), of ``name``."""
        return [a for a in self.api("alerts")["alerts"] if name is None or a["labels"]["alertname"] == name]

    def targets(self) -> list[dict]:
        """The active targets, each with ``health`` and ``lastError``."""
        return self.api("targets")["activeTargets"]

    def stop(self) -> int:
        """SIGTERM, then SIGKILL if it has not ended in 10 s; its exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return self.proc.returncode


def wait_scrape(prom: PromServer, after: float, timeout_s: float = 15.0) -> None:
    """Until Prometheus holds a successful scrape of the relay taken after ``after`` (Unix time, s)."""
    def scraped() -> bool:
        return any(float(s["value"][1]) > after for s in prom.query(f'timestamp(up{{job="{JOB}"}} == 1)'))
    try:
        wait_for(scraped, timeout_s, 0.2, f"a successful scrape of the relay after {after}")
    except AssertionError as exc:
        errors = [t["lastError"] for t in prom.targets() if t["labels"]["job"] == JOB]
        raise AssertionError(f"{exc}; the scrape's last error: {errors}") from None
