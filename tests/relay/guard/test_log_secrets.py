"""No secret in any log line at any level (issue 61, item 2): a real relay process at ``--log-level DEBUG``
(every library's lines: aiohttp's, Engine.IO's and Socket.IO's packets) with an admin token, viewer
tokens and node tokens, and every place a credential can travel driven with good and bad ones: a
query, an ``Authorization`` header, the session cookie, Socket.IO's ``auth``, an event's data and
name, a node's hello and its resume secret. None of them is in the relay's output.
"""

from __future__ import annotations

import asyncio
import secrets
import urllib.error
import urllib.parse
import urllib.request

import socketio

from dcuscope.relay.guard.policy import COOKIE
from tests.relay.helpers import HandNode, RelayProcess, finish_node, start_node


def secret() -> str:
    return "s" + secrets.token_hex(12)


def status(url: str, headers: dict | None = None, data: bytes | None = None) -> tuple[int, dict]:
    request = urllib.request.Request(url, headers=headers or {}, data=data)
    opener = urllib.request.build_opener(NoRedirect)
    try:
        with opener.open(request, timeout=10) as r:
            return r.status, dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers)


class NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):
        return None


async def socketio_client(url: str, auth: dict | None, headers: dict | None = None) -> socketio.AsyncClient | None:
    sio = socketio.AsyncClient(reconnection=False)
    try:
        await sio.connect(url, auth=auth, headers=headers or {}, namespaces=["/ui"], transports=["websocket"],
                          wait_timeout=5)
    except socketio.exceptions.ConnectionError:
        return None
    return sio


def test_no_credential_reaches_the_log_at_debug(tmp_path):
    admin, viewer, node_token = secret(), secret(), secret()
    (tmp_path / "viewers.txt").write_text(f"grafana {viewer}\n")
    (tmp_path / "nodes.txt").write_text(f"DCU-1 {node_token}\n")
    wrong = {place: secret() for place in ("query", "header", "cookie", "sio-auth", "event-data", "event-name",
                                            "hello-token", "hello-secret", "ingest-query")}
    relay = RelayProcess(tmp_path / "relay.db", token=admin,
                         args=["--log-level", "DEBUG", "--viewer-tokens", str(tmp_path / "viewers.txt"),
                               "--node-tokens", str(tmp_path / "nodes.txt")])
    url = relay.url
    try:
        # A query: the page's old way in, a wrong one, an old node's ?token= at /ingest.
        code, headers = status(f"{url}/?token={viewer}")
        assert code == 303 and COOKIE in headers.get("Set-Cookie", ""), (code, headers)
        cookie = headers["Set-Cookie"].split(";")[0]
        assert status(f"{url}/?token={wrong['query']}")[0] in (303, 401, 403)
        assert status(f"{url}/ingest?token={wrong['ingest-query']}")[0] == 401
        # A header and a cookie, good and bad.
        assert status(f"{url}/api/health", {"Authorization": f"Bearer {admin}"})[0] == 200
        assert status(f"{url}/api/health", {"Authorization": f"Bearer {wrong['header']}"})[0] == 401
        assert status(f"{url}/api/health", {"Cookie": cookie})[0] == 200
        assert status(f"{url}/api/health", {"Cookie": f"{COOKIE}={wrong['cookie']}"})[0] == 401
        form = urllib.parse.urlencode({"token": viewer}).encode()
        assert status(f"{url}/signin", {"Origin": url, "Content-Type": "application/x-www-form-urlencoded"},
                      form)[0] == 204

        async def browsers():
            # Socket.IO's auth (a page passes its token there), an event's data and its name.
            good = await socketio_client(url, {"token": viewer}, {"Authorization": f"Bearer {viewer}"})
            assert good is not None
            await good.call("subscribe", {"nodes": ["DCU-1"], "token": wrong["event-data"]}, namespace="/ui", timeout=5)
            await good.emit(wrong["event-name"], {"auth": viewer}, namespace="/ui")
            await asyncio.sleep(0.3)
            await good.disconnect()
            assert await socketio_client(url, {"token": wrong["sio-auth"]}) is None

        asyncio.run(browsers())

        async def nodes():
            # A hand node's hello with a stray token in it, then the run resumed with its secret,
            # then a forged secret for it.
            first = await HandNode.open(url, "DCU-1", "a" * 32, token=node_token)
            resume = first.secret
            await first.close()
            again = await HandNode.open(url, "DCU-1", "a" * 32, token=node_token, secret=resume)
            await again.close()
            try:
                forged = await HandNode.open(url, "DCU-1", "a" * 32, token=node_token, secret=wrong["hello-secret"])
                await forged.close()
            except (AssertionError, ConnectionError, OSError):
                pass
            try:
                await HandNode.open(url, "DCU-1", "b" * 32, token=wrong["hello-token"])
            except Exception:  # noqa: BLE001 - refused, as it should be
                pass
            return resume

        resume = asyncio.run(nodes())
        # A real node streaming with its token.
        node = start_node(url, "DCU-1", tmp_path / "node.npz", frames=30, token=node_token)
        counters = finish_node(node, 60)
        assert counters["acked"] == counters["events"], counters
    finally:
        relay.stop()
    text = relay.log.read_text(errors="replace")
    # The log is a DEBUG one with the libraries' packet lines in it: there was something to leak.
    assert "Received packet" in text and "Sending packet" in text and "DEBUG" in text, text[-2000:]
    leaked = {name: value for name, value in {"admin": admin, "viewer": viewer, "node": node_token, "resume": resume,
                                              "cookie": cookie.split("=", 1)[1], **wrong}.items() if value in text}
    assert not leaked, [line for line in text.splitlines() if any(v in line for v in leaked.values())][:10]
