"""The relay's paths to its servers over TLS, each against the real server with TLS on and certificates
of a private CA (tests/tlscerts.py): PostgreSQL 15 with ``sslmode=verify-full`` (tests/pgserver.py).
A server the relay cannot verify (another CA's certificate, another name) is one line, never a traceback,
and no secret of the URL is ever printed."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from urllib.parse import quote, urlsplit

import pytest

from dcuscope.cli import main as cli_main
from tests.conftest import cli_env
from tests.pgserver import PASSWORD, PostgresServer
from tests.redisserver import RedisServer
from tests.relay.otlpreceiver import OtlpReceiver
from tests.relay.helpers import RelayProcess, finish_node, get_json, load_node, start_node, stored_equals_sent, wait_for
from tests.relay.api.test_fanout import Browser
from tests.tlscerts import TestCA

SECRETS = (PASSWORD, "s3cret")


@pytest.fixture(scope="module")
def cas(tmp_path_factory):
    """(the CA the servers' certificates come from, another CA)."""
    folder = tmp_path_factory.mktemp("cas")
    return TestCA(folder), TestCA(folder, "other")


@pytest.fixture(scope="module")
def tls_postgres(cas):
    """A PostgreSQL server taking TLS connections only, its certificate for 127.0.0.1 and localhost."""
    server = PostgresServer(tls=cas[0].issue("postgres")).start()
    yield server
    server.close()


def one_line_error(done: subprocess.CompletedProcess, says: str) -> None:
    assert done.returncode == 2 and says in done.stderr, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
    assert not any(s in done.stderr + done.stdout for s in SECRETS)


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dcuscope.cli", *args], capture_output=True, text=True,
                          timeout=60, env=cli_env())


def test_a_relay_stores_over_verify_full_and_refuses_a_server_it_cannot_verify(tmp_path, cas, tls_postgres):
    ca, other = cas
    database = urlsplit(tls_postgres.new_database()).path.lstrip("/")
    url = tls_postgres.user_url(database, ca.cert)
    assert "sslmode=verify-full" in url
    relay = RelayProcess(url, log=tmp_path / "relay.log")
    try:
        counters = finish_node(start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=100))
    finally:
        assert relay.stop() == 0
    assert counters["acked"] == counters["events"] and counters["lost"] == 0
    stored_equals_sent(url, "DCU-1", load_node(tmp_path / "n.npz")[1])
    assert not any(s in (tmp_path / "relay.log").read_text() for s in SECRETS)
    # Every command taking --db reaches it the same way.
    compacted = cli("db", "compact", url, "--after", "0")
    assert compacted.returncode == 0 and "compacted" in compacted.stdout, compacted.stderr
    assert not any(s in compacted.stderr + compacted.stdout for s in SECRETS)

    wrong_ca = subprocess.run([sys.executable, "-m", "dcuscope.relay", "--port", "0", "--db",
                               tls_postgres.user_url(database, other.cert)],
                              capture_output=True, text=True, timeout=60, env=cli_env())
    one_line_error(wrong_ca, "SSL error: certificate verify failed")
    # The certificate names 127.0.0.1 and localhost: reached as db.example (at 127.0.0.1), it is refused.
    # The password given as libpq's query parameter instead is not printed either.
    named = tls_postgres.user_url(database, ca.cert, host="db.example")
    in_query = named.replace(f":{quote(PASSWORD, safe='')}@", "@") + f"&hostaddr=127.0.0.1&password={quote(PASSWORD)}"
    wrong_name = cli("db", "compact", in_query)
    one_line_error(wrong_name, 'does not match host name "db.example"')


@pytest.fixture(scope="module")
def tls_redis(cas):
    server = RedisServer(tls=cas[0].issue("redis")).start()
    yield server
    server.close()


def test_relays_on_a_rediss_redis_reach_each_others_browsers_and_refuse_another_ca(tmp_path, cas, tls_postgres,
                                                                                   tls_redis):
    ca, other = cas
    assert tls_redis.url.startswith("rediss://")
    url = tls_postgres.new_database()
    relays = [RelayProcess(url, log=tmp_path / f"{name}.log", args=["--redis", tls_redis.url, "--redis-ca", str(cert),
                                                                     "--name", name])
              for name, cert in (("relay-a", ca.cert), ("relay-b", ca.cert), ("relay-c", other.cert))]
    a, b, c = relays
    try:
        node = start_node(a.url, "DCU-A", tmp_path / "a.npz", frames=200, fps=40, paced=True, linger=True)
        wait_for(lambda: [n["node"] for n in get_json(f"{b.url}/api/nodes")] == ["DCU-A"], 30, what="B lists A's DCU")

        async def watch() -> Browser:
            browser = Browser()
            await browser.open(b.url, ["DCU-A"])
            for _ in range(200):  # within a second unloaded
                if browser.frames("DCU-A"):
                    break
                await asyncio.sleep(0.1)
            await browser.sio.disconnect()
            return browser

        # A's pushes of its DCU's frames reached B's browser through Redis over TLS.
        assert asyncio.run(watch()).frames("DCU-A")
        finish_node(node)
        fanout = {r: get_json(f"{r.url}/api/health")["fanout"] for r in relays}
        assert fanout[a]["ok"] and fanout[b]["ok"] and fanout[b]["received"] > 0, fanout
        # C does not trust the server's CA: never connected, it says why, and it serves on. (On a loaded
        # machine a try can time out before the handshake fails: the next one says why.)
        wait_for(lambda: "certificate verify failed" in (get_json(f"{c.url}/api/health")["fanout"]["error"] or ""), 30,
                 what="relay-c says the certificate failed")
        assert not get_json(f"{c.url}/api/health")["fanout"]["ok"]
        assert get_json(f"{c.url}/api/health")["relay"] == "relay-c"
    finally:
        for relay in relays:
            relay.stop()
    lines = [ln for ln in (tmp_path / "relay-c.log").read_text().splitlines() if "redis" in ln.lower()]
    # One line for the outage, not one for each try: it names the first try's reason (the refused certificate,
    # or on a loaded machine a timeout before the handshake failed; /api/health said the certificate above).
    assert len(lines) == 1 and ("certificate verify failed" in lines[0] or "Timeout" in lines[0]), lines


@pytest.mark.parametrize("args, says", [
    (["--redis", "redis://127.0.0.1:6379/0", "--redis-ca", "ca.pem"], "give a rediss:// URL"),
    (["--redis-ca", "ca.pem"], "--redis-ca needs --redis rediss://"),
    (["--redis", "rediss://127.0.0.1:6379/0", "--redis-ca", "missing.pem"], "--redis-ca missing.pem: No such file"),
    (["--otlp", "http://c:4318", "--otlp-ca", "ca.pem"], "give an https:// --otlp URL"),
    (["--otlp-ca", "ca.pem"], "--otlp-ca needs --otlp URL"),
    (["--otlp", "https://c:4318", "--otlp-ca", "missing.pem"], "--otlp-ca missing.pem: No such file"),
])
def test_bad_tls_options_get_a_one_line_error(tmp_path, capsys, args, says):
    assert cli_main(["relay", "--port", "0", "--db", str(tmp_path / "r.db"), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err, err


def test_otlp_over_https_checks_the_collectors_certificate(tmp_path, cas):
    ca, other = cas
    with OtlpReceiver(tls=ca.issue("collector")) as receiver:
        assert receiver.url.startswith("https://")
        relays = {cert: RelayProcess(tmp_path / f"{name}.db", args=["--otlp", receiver.url, "--otlp-ca", str(cert),
                                                                   "--otlp-every", "1", "--otlp-timeout", "2"])
                  for name, cert in (("good", ca.cert), ("other", other.cert))}
        try:
            nodes = [start_node(r.url, "DCU-1", tmp_path / f"{i}.npz", frames=150) for i, r in enumerate(relays.values())]
            sent = [finish_node(n) for n in nodes]
            trusting = relays[ca.cert].url

            def all_exported() -> dict | None:  # 1 in 1: every frame the relay finalised
                finalised = get_json(f"{trusting}/api/nodes")[0]["frames"]["finalised"]
                otlp = get_json(f"{trusting}/api/health")["otlp"]
                return otlp if 0 < finalised == otlp["frames_exported"] else None

            good = wait_for(all_exported, 30, 0.2, "the trusted collector took every finalised frame")
            bad = wait_for(lambda: (lambda o: o if o["dropped"]["export_failed"] else None)(
                get_json(f"{relays[other.cert].url}/api/health")["otlp"]), 30, 0.2, "an export to the untrusted collector failed")
            alive = [r.alive() for r in relays.values()]
        finally:
            codes = [r.stop() for r in relays.values()]
    assert all(s["acked"] == s["events"] and s["lost"] == 0 for s in sent) and all(alive) and codes == [0, 0]
    assert good["frames_exported"] == sum(good["frames"].values()) and good["dropped"]["export_failed"] == 0
    # Every span the receiver decoded came from the relay that trusts its CA: the other sent none.
    assert good["spans_exported"] == len(receiver.spans) > 0 and receiver.refused == []
    assert bad["frames_exported"] == 0
    lines = [ln for ln in relays[other.cert].log.read_text().splitlines() if "OTLP" in ln or "opentelemetry" in ln]
    assert len(lines) == 1 and "failing" in lines[0] and "CERTIFICATE_VERIFY_FAILED" in lines[0], lines
