"""TLS on the relay's port (issue 47): real relay processes with certificates made at test time
(:mod:`tests.tlscerts`), real simulated nodes, and every refusal seen from both sides: the node's
one line naming the relay and the reason, the relay's count.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import signal
import socket
import ssl
import urllib.request

import aiohttp
import pytest

from dcuscope.model.delays import node_stats
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.probes.ship.relaylink import Link
from dcuscope.protocol.wire import MAX_MESSAGE_BYTES
from tests.relay.helpers import (HandNode, RelayProcess, assert_stats_equal, finish_node, get_json, load_node,
                                 read_http_answer, start_node, wait_for)
from tests.tlscerts import TestCA, served_serial

HEADER_S = 1.0
PER_PEER = 16
"""The relay's default connections_per_peer."""
VIEWER = "viewer-token-0123456789"
"""The module relay's viewer (--viewer-tokens): what browsers, the tests and Prometheus read with."""
PROXY = "127.0.0.9"
"""The module relay's trusted proxy: its connections start with a PROXY header, then TLS."""


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pki")
    ca, other = TestCA(folder), TestCA(folder, "other")
    return {"folder": folder, "ca": ca, "other": other, "server": ca.issue("relay"),
            "dcu1": ca.issue("DCU-1", client=True), "dcu3": ca.issue("DCU-3", client=True),
            "stranger": other.issue("DCU-1", client=True)}


@pytest.fixture(scope="module")
def relay(pki, tmp_path_factory):
    """A relay that speaks TLS only and takes nodes with a certificate of ``pki``'s CA."""
    server = pki["server"]
    viewers = tmp_path_factory.mktemp("viewers") / "viewers.txt"
    viewers.write_text(f"prometheus {VIEWER}\n")
    proc = RelayProcess(tmp_path_factory.mktemp("tls") / "relay.db",
                        args=["--tls-cert", str(server.cert), "--tls-key", str(server.key),
                              "--tls-client-ca", str(pki["ca"].cert), "--limit", f"header_timeout_s={HEADER_S}",
                              "--trusted-proxy", PROXY, "--viewer-tokens", str(viewers)])
    yield proc
    proc.stop()


def node_tls(pki, cert: str | None = "dcu1") -> RelayTls:
    issued = pki[cert] if cert else None
    return RelayTls(str(pki["ca"].cert), str(issued.cert) if issued else None, str(issued.key) if issued else None)


def node_args(pki, cert: str = "dcu1") -> list[str]:
    return ["--relay-ca", str(pki["ca"].cert), "--relay-cert", str(pki[cert].cert), "--relay-key", str(pki[cert].key)]


def browser(pki) -> ssl.SSLContext:
    """What a browser that trusts the CA has: no client certificate."""
    return ssl.create_default_context(cafile=str(pki["ca"].cert))


async def connect(url: str, tls: RelayTls) -> str:
    """Why a node with ``tls`` cannot open its WebSocket to ``url`` ("" when it can)."""
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(ssl=tls.context())) as session:
        try:
            link = await Link.open(session, url, None, lambda ack: None)
        except ExportError as exc:
            return str(exc)
        await link.close()
        return ""


def health(relay: RelayProcess, pki) -> dict:
    return get_json(f"{relay.url}/api/health", VIEWER, context=browser(pki))


def test_a_node_streams_over_tls_and_each_refusal_has_its_reason(relay, pki, tmp_path):
    assert relay.url.startswith("https://")
    node = start_node(relay.url, "DCU-1", tmp_path / "good.npz", frames=100, extra=node_args(pki))

    # A plaintext request to the TLS port: a short answer, never served.
    with socket.create_connection(("127.0.0.1", relay.port), 10) as s:
        s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        status, body = read_http_answer(s)
    assert status == 400 and b"HTTPS" in body, (status, body)

    # A handshake that stalls after its first bytes: closed by the relay, within a bounded wait.
    with socket.create_connection(("127.0.0.1", relay.port), 10) as s:
        s.sendall(b"\x16\x03\x01")
        s.settimeout(HEADER_S + 10)
        assert s.recv(1024) == b""

    # The hostile clients of test_hostile_connections, over TLS: a flood of stalled handshakes from
    # one address holds at most its per-address share (idle ones make room), an oversize frame
    # closes its own connection only.
    flood = []
    for _ in range(3 * PER_PEER):
        s = socket.create_connection(("127.0.0.1", relay.port), 10, source_address=("127.0.0.7", 0))
        s.sendall(b"\x16\x03\x01")
        flood.append(s)
    # Evicted connections leave on the relay's next loop turns: what the relay holds settles at its cap.
    held = wait_for(lambda: (h := health(relay, pki))["connections"]["tcp"] <= PER_PEER + 3 and h, 5,
                    what="the flood held to its per-address share")
    for s in flood:
        s.close()
    assert held["refused"]["peer_cap"] >= 2 * PER_PEER, held["refused"]
    reply = asyncio.run(oversize(relay.url, node_tls(pki, "dcu3").context()))
    assert health(relay, pki)["rejected"] >= 1
    # Over TLS the hello reply carries the UDP clock exchange's secret (tests/relay/clock/test_clock_udp.py: none over ws).
    assert len(bytes.fromhex(reply["clock_secret"])) == 32, reply

    async def refusals() -> dict[str, str]:
        stranger = node_tls(pki, "stranger")
        return {"no certificate": await connect(relay.url, node_tls(pki, None)),
                "another CA's certificate": await connect(relay.url, stranger),
                "unknown CA": await connect(relay.url, RelayTls()),  # the system's CAs do not know ours
                "DCU-1 as DCU-2": await as_another(relay.url, node_tls(pki).context())}
    why = asyncio.run(refusals())
    assert "HTTP 403" in why["no certificate"] and "--relay-cert" in why["no certificate"], why
    assert why["another CA's certificate"].startswith("TLS: the relay closed the connection after the handshake"), why
    assert why["unknown CA"].startswith("TLS: the relay's certificate failed verification"), why
    assert "issuer" in why["unknown CA"] or "self-signed" in why["unknown CA"], why
    assert "DCU-2" in why["DCU-1 as DCU-2"] and "DCU-1" in why["DCU-1 as DCU-2"], why

    counters = finish_node(node, 60)
    assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
    # Its clock samples came over UDP, tagged with that secret: the relay answered them all, found no bad tag.
    assert counters["clock_via"] == "udp" and counters["clock_forged"] == 0, counters
    udp = health(relay, pki)["clock_udp"]
    assert udp["answered"] >= 16 and udp["bad_tag"] == 0, udp
    header, events = load_node(tmp_path / "good.npz")
    url = f"{relay.url}/api/stats?node=DCU-1"
    wait_for(lambda: get_json(f"{relay.url}/api/nodes", VIEWER, context=browser(pki))[0]["ended"], 10, what="the run's end")
    assert_stats_equal(node_stats(header, events), get_json(url, VIEWER, context=browser(pki)))

    refused = health(relay, pki)["refused"]
    assert refused["plaintext"] >= 1 and refused["tls_timeout"] >= 1 and refused["tls_handshake"] >= 1, refused
    with pytest.raises(OSError):  # no certificate of the CA: no handshake
        get_json(f"{relay.url}/api/health", VIEWER, context=ssl.create_default_context())
    metrics = _get_text(f"{relay.url}/metrics", browser(pki))
    assert f'dcuscope_relay_refused_total{{reason="plaintext"}} {refused["plaintext"]}' in metrics, metrics[-2000:]


async def as_another(url: str, context: ssl.SSLContext) -> str:
    """The error a node with DCU-1's certificate gets when it says hello as DCU-2."""
    try:
        node = await HandNode.open(url, "DCU-2", "0" * 32, ssl=context)
    except ConnectionError as exc:
        return str(exc)
    await node.close()
    return ""


async def oversize(url: str, context: ssl.SSLContext) -> dict:
    """A binary frame over the relay's bound: the relay closes the connection (within 10 s). The
    relay's hello reply."""
    node = await HandNode.open(url, "DCU-3", "3" * 32, ssl=context)
    try:
        await node.link.send_batch(b"\0" * (MAX_MESSAGE_BYTES + 1))
        await asyncio.wait_for(node.link.closed(), 10)
    finally:
        await node.close()
    return node.reply


def _get_text(url: str, context: ssl.SSLContext) -> str:
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {VIEWER}"})
    with urllib.request.urlopen(request, timeout=10, context=context) as r:
        return r.read().decode()


def test_a_trusted_proxys_connection_carries_its_header_before_tls(relay, pki):
    def via_proxy(header: bytes) -> dict | None:
        """/api/health through a connection from the proxy starting with ``header`` (None: closed)."""
        with socket.create_connection(("127.0.0.1", relay.port), 10, source_address=(PROXY, 0)) as raw:
            raw.sendall(header)
            try:
                with browser(pki).wrap_socket(raw, server_hostname="127.0.0.1") as tls:
                    tls.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n"
                                b"Authorization: Bearer " + VIEWER.encode() + b"\r\n\r\n")
                    status, body = read_http_answer(tls)
            except OSError:
                return None
        assert status == 200, (status, body)
        return json.loads(body)

    before = health(relay, pki)
    answer = via_proxy(b"PROXY TCP4 10.1.2.3 127.0.0.1 5555 443\r\n")
    assert answer is not None and answer["proxy"]["proxied"] == before["proxy"]["proxied"] + 1, answer["proxy"]
    assert via_proxy(b"GARBAGE\r\n") is None
    assert health(relay, pki)["refused"]["proxy_header"] == before["refused"]["proxy_header"] + 1


def test_failover_past_an_unknown_ca_and_a_renewed_certificate(relay, pki, tmp_path):
    """Relay A first shows a certificate of a CA the node does not know: the node says so in one
    line and completes its run on relay B. Then A's files are replaced and A gets SIGHUP: an expired
    certificate, one for another name, a file that cannot be loaded (A keeps the one in use), a good one."""
    cert, key = tmp_path / "a.pem", tmp_path / "a.key"

    def install(issued) -> None:
        shutil.copy(issued.cert, cert)
        shutil.copy(issued.key, key)

    install(pki["other"].issue("relay"))
    a = RelayProcess(tmp_path / "a.db", args=["--tls-cert", str(cert), "--tls-key", str(key)])
    try:
        node = start_node(f"{a.url},{relay.url}", "DCU-1", tmp_path / "failover.npz", frames=60, extra=node_args(pki))
        out, err = node.communicate(timeout=60)
        stderr = err.decode()
        assert node.returncode == 0, stderr[-3000:]
        counters = json.loads(out.decode().strip().splitlines()[-1])
        assert counters["acked"] == counters["events"] and counters["lost"] == 0, counters
        header, events = load_node(tmp_path / "failover.npz")
        run = wait_for(lambda: [r for r in get_json(f"{relay.url}/api/nodes", VIEWER, context=browser(pki))
                                if r.get("run") == counters["run"] and r["ended"]], 10, what="the run on relay B")
        assert run, counters
        # Relay B's newest run of DCU-1 is this one: stored == sent.
        assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=DCU-1",
                                                                VIEWER, context=browser(pki)))
        said = [line for line in stderr.splitlines() if a.url in line and "relays tried:" not in line]  # not the summary
        assert len(said) == 1 and "failed verification" in said[0], stderr
        print("\nthe node said:", *said, sep="\n")

        ca = pki["ca"]

        def renew(issued, expect: str) -> None:
            before = served_serial(a.port)
            install(issued)
            a.proc.send_signal(signal.SIGHUP)
            wait_for(lambda: served_serial(a.port) != before, 10, what="the renewed certificate")
            why = asyncio.run(connect(a.url, node_tls(pki, None)))
            assert expect in why if expect else why == "", (expect, why)

        renew(ca.issue("relay", expired=True), "certificate has expired")
        renew(ca.issue("relay", ip=None), "IP address mismatch")
        in_use = served_serial(a.port)
        cert.write_text("not a certificate\n")
        a.proc.send_signal(signal.SIGHUP)
        wait_for(lambda: "keeping the certificate in use" in a.log.read_text(), 10, what="the relay's log line")
        assert served_serial(a.port) == in_use
        renew(ca.issue("relay"), "")
        assert len([line for line in a.log.read_text().splitlines() if "keeping" in line]) == 1
    finally:
        a.stop()


def test_prometheus_scrapes_metrics_over_https_with_a_viewers_bearer_token(relay, pki, tmp_path):
    """Debian's Prometheus, configured as configs/prometheus/prometheus.yml's HTTPS job says (scheme
    https, tls_config.ca_file, a viewer's token in credentials_file), scrapes the TLS relay; the same
    job without the token is refused (401), and one over plain HTTP gets the relay's plaintext refusal."""
    from tests.relay.promserver import JOB, PromServer

    target = f"127.0.0.1:{relay.port}"
    tls = {"scheme": "https", "tls_config": {"ca_file": str(pki["ca"].cert)}}
    others = [{"job_name": "no-token", "static_configs": [{"targets": [target]}], **tls},
              {"job_name": "plain-http", "static_configs": [{"targets": [target]}]}]
    prom = PromServer(tmp_path / "prom", target, VIEWER, extra_jobs=others, tls_ca=pki["ca"].cert)
    try:
        health_of = wait_for(lambda: (h := {t["labels"]["job"]: t for t in prom.targets() if t["health"] != "unknown"})
                             and len(h) == 3 and h, 20, 0.5, "every job scraped once")
        assert health_of[JOB]["health"] == "up" and health_of[JOB]["scrapeUrl"].startswith("https://"), health_of[JOB]
        assert health_of["no-token"]["health"] == "down" and "401" in health_of["no-token"]["lastError"], health_of
        assert health_of["plain-http"]["health"] == "down" and "400" in health_of["plain-http"]["lastError"], health_of
        events = prom.values(f'dcuscope_relay_events_total{{job="{JOB}"}}', "job")
        assert events.get(JOB, 0) > 0, events  # the first test's node streamed through this relay
    finally:
        prom.stop()
