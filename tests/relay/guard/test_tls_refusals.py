"""Certificate refusals that say why (issue 61, item 3): a relay with ``--tls-client-ca`` at its default
log level, real TLS handshakes from nodes' certificates that are expired, not yet valid, from an
unknown CA and for the wrong purpose (certificates made at test time, :mod:`tests.tlscerts`).

The relay's line names the verifier's reason, and the first line of each reason from each address is
never held back by the log's rate bound; a node says what is wrong with its own certificate, date
included, in one line before it connects.
"""

from __future__ import annotations

import argparse
import logging
import socket
import ssl
import subprocess

import pytest

from dcuscope.probes.ship import nodetls
from tests.relay.helpers import RelayProcess, start_node, wait_for
from tests.tlscerts import TestCA

REPEATS = 10
"""The relay's default log_repeats_per_min: lines of one message a minute before the rest are held back."""


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pki")
    ca, other = TestCA(folder), TestCA(folder, "other")
    return {"ca": ca, "server": ca.issue("relay"),
            "expired": ca.issue("DCU-1", client=True, expired=True),
            "future": ca.issue("DCU-2", client=True, not_yet_valid=True),
            "stranger": other.issue("DCU-3", client=True),
            "server-only": ca.issue("DCU-4")}  # extendedKeyUsage serverAuth: not a client's


@pytest.fixture(scope="module")
def relay(pki, tmp_path_factory):
    server = pki["server"]
    proc = RelayProcess(tmp_path_factory.mktemp("relay") / "relay.db",
                        args=["--tls-cert", str(server.cert), "--tls-key", str(server.key),
                              "--tls-client-ca", str(pki["ca"].cert)])
    yield proc
    proc.stop()


def handshake(relay: RelayProcess, pki, cert: str, source: str) -> None:
    """A TLS client with ``cert`` from ``source``, as far as the relay lets it (it sends a request:
    under TLS 1.3 the relay's refusal comes after the client's side of the handshake is done)."""
    context = ssl.create_default_context(cafile=str(pki["ca"].cert))
    context.load_cert_chain(str(pki[cert].cert), str(pki[cert].key))
    with socket.create_connection(("127.0.0.1", relay.port), 10, source_address=(source, 0)) as raw:
        try:
            with context.wrap_socket(raw, server_hostname="127.0.0.1") as tls:
                tls.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                assert tls.recv(1024) == b"", f"the relay served {cert}"
        except (ssl.SSLError, ConnectionResetError):
            pass


def lines(relay: RelayProcess, *parts: str) -> list[str]:
    return [line for line in relay.log.read_text(errors="replace").splitlines() if all(p in line for p in parts)]


def test_the_relays_line_names_the_reason_and_the_first_of_each_per_address_is_never_held_back(relay, pki):
    said = {"expired": 'its certificate expired; the verifier said "certificate has expired" (X509 error 10)',
            "future": 'its certificate is not valid yet; the verifier said "certificate is not yet valid" (X509 error 9)',
            "stranger": "unknown CA: its certificate comes from a CA that --tls-client-ca does not hold; the "
                        'verifier said "unable to get local issuer certificate" (X509 error 20)',
            "server-only": "wrong purpose: its certificate is not for client authentication (clientAuth); the "
                           'verifier said "unsuitable certificate purpose" (X509 error 26)'}
    for cert, reason in said.items():
        handshake(relay, pki, cert, "127.0.0.41")
        wait_for(lambda: lines(relay, "TLS handshake with 127.0.0.41 failed: refused the client certificate:", reason),
                 10, what=f"the relay's line for {cert}")
    # One address refused many times over for one reason: past the rate bound, then another reason
    # from it, and the first reason from another address: each one's first line is written.
    for _ in range(REPEATS + 5):
        handshake(relay, pki, "stranger", "127.0.0.42")
    handshake(relay, pki, "expired", "127.0.0.42")
    handshake(relay, pki, "stranger", "127.0.0.43")
    for source, reason in (("127.0.0.42", said["expired"]), ("127.0.0.43", said["stranger"])):
        wait_for(lambda: lines(relay, f"TLS handshake with {source} failed", reason), 10,
                 what=f"the first line of its reason from {source}")
    assert len(lines(relay, "TLS handshake with 127.0.0.42 failed", said["stranger"])) == REPEATS
    assert "WARNING" in lines(relay, "127.0.0.43", said["stranger"])[0]  # at the default log level


@pytest.mark.parametrize("cert, problem", [
    ("expired", "is expired on 2000-01-02 00:00:00 UTC"),
    ("future", "is not valid before 2099-01-01 00:00:00 UTC"),
    ("server-only", "is not for client authentication (its extendedKeyUsage is serverAuth: it needs clientAuth)"),
])
def test_a_node_says_what_is_wrong_with_its_own_certificate(pki, cert, problem, caplog):
    args = argparse.Namespace(relay_ca=str(pki["ca"].cert), relay_cert=str(pki[cert].cert),
                              relay_key=str(pki[cert].key))
    with caplog.at_level(logging.WARNING, logger=nodetls.__name__):
        nodetls.tls_from_args(args)
        nodetls.tls_from_args(args)  # a command that reads its options twice says it once
    assert [r.getMessage() for r in caplog.records] == [
        f"--relay-cert {pki[cert].cert} {problem}: a relay that asks nodes for a certificate (--tls-client-ca) "
        "will refuse it"]


def test_a_node_with_a_good_certificate_says_nothing_and_an_expired_one_one_line(relay, pki, tmp_path):
    good = TestCA(tmp_path).issue("DCU-9", client=True)
    args = argparse.Namespace(relay_ca=None, relay_cert=str(good.cert), relay_key=str(good.key))
    assert nodetls.check_own_certificate(args.relay_cert) is None
    node = start_node(relay.url, "DCU-1", tmp_path / "expired.npz", frames=5,
                      extra=["--relay-ca", str(pki["ca"].cert), "--relay-cert", str(pki["expired"].cert),
                             "--relay-key", str(pki["expired"].key), "--close-timeout", "1"])
    try:
        _, err = node.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        node.kill()
        raise
    said = [line for line in err.decode().splitlines() if "is expired on 2000-01-02 00:00:00 UTC" in line]
    assert len(said) == 1 and str(pki["expired"].cert) in said[0], err.decode()[-2000:]
