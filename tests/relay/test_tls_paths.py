"""The relay's paths to its servers over TLS, each against the real server with TLS on and certificates
of a private CA (tests/tlscerts.py): PostgreSQL 15 with ``sslmode=verify-full`` (tests/pgserver.py).
A server the relay cannot verify (another CA's certificate, another name) is one line, never a traceback,
and no secret of the URL is ever printed."""

from __future__ import annotations

import subprocess
import sys
from urllib.parse import quote, urlsplit

import pytest

from tests.conftest import cli_env
from tests.pgserver import PASSWORD, PostgresServer
from tests.relay.helpers import RelayProcess, finish_node, load_node, start_node
from tests.relay.test_fleet import stored_equals_sent
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

    wrong_ca = subprocess.run([sys.executable, "-m", "relay", "--port", "0", "--db",
                               tls_postgres.user_url(database, other.cert)],
                              capture_output=True, text=True, timeout=60, env=cli_env())
    one_line_error(wrong_ca, "SSL error: certificate verify failed")
    # The certificate names 127.0.0.1 and localhost: reached as db.example (at 127.0.0.1), it is refused.
    # The password given as libpq's query parameter instead is not printed either.
    named = tls_postgres.user_url(database, ca.cert, host="db.example")
    in_query = named.replace(f":{quote(PASSWORD, safe='')}@", "@") + f"&hostaddr=127.0.0.1&password={quote(PASSWORD)}"
    wrong_name = cli("db", "compact", in_query)
    one_line_error(wrong_name, 'does not match host name "db.example"')
