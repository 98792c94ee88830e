"""The access policy (relay/guard/policy.py): every route and /ui event against every role, the
session cookie, client certificates, and refusals counted and logged without a credential."""

from __future__ import annotations

import asyncio
import logging

import aiohttp
import pytest
import socketio

from dcuscope.relay.api.ui import UiNamespace
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.guard.auth import Credentials
from dcuscope.relay.guard.policy import COOKIE, COOKIE_LIFETIME_S, Action, Policy, Principal, Role, actions, certificate_principal
from dcuscope.relay.server import start_relay

ADMIN = "admin-token-0123456789"
VIEWER = "viewer-token-0123456789"
NODE = "node-token-0123456789ab"
CREDENTIALS = {"none": None, "wrong": "wrong-token-0123456789", "admin": ADMIN, "viewer": VIEWER, "node": NODE}
# What each role gets for each action: "ok" (anything but 401/403) or the refusal's status.
EXPECTED = {
    Action.PUBLIC: {"none": "ok", "wrong": "ok", "admin": "ok", "viewer": "ok", "node": "ok"},
    Action.READ: {"none": 401, "wrong": 401, "admin": "ok", "viewer": "ok", "node": 403},
    Action.INGEST: {"none": 401, "wrong": 401, "admin": "ok", "viewer": 401, "node": "ok"},
    Action.SOCKET: {"none": "ok", "wrong": "ok", "admin": "ok", "viewer": "ok", "node": "ok"},
}
UI_CONNECTS = {"none": False, "wrong": False, "admin": True, "viewer": True, "node": False}
UI_EVENTS = {"connect", "disconnect", "subscribe"}
"""Every event the /ui namespace handles: only connect is open to a client that is not yet let in."""
SAMPLE_PATHS = {"/api/sessions/{session}/nodes": "/api/sessions/1/nodes",
                "/api/sessions/{session}/frames": "/api/sessions/1/frames",
                "/api/sessions/{session}/stats": "/api/sessions/1/stats", "/": "/", "/socket.io/": "/socket.io/"}


def _status_kind(status: int) -> int | str:
    return status if status in (401, 403) else "ok"


async def _walk(tmp_path, caplog) -> tuple[dict, dict, dict, list[str], dict]:
    relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", credentials=Credentials(ADMIN, {"ann": VIEWER}, {"DCU-1": NODE}),
                              clock_port=0))
    url = f"http://127.0.0.1:{relay.port}"
    app = relay.runner.app
    declared = actions(app)
    undeclared = [r.canonical for r in app.router.resources() if r not in declared]
    got: dict = {}
    try:
        async with aiohttp.ClientSession() as http:
            for resource in app.router.resources():
                if resource not in declared:
                    continue
                canonical = resource.canonical
                path = SAMPLE_PATHS.get(canonical, canonical if "{" not in canonical else None)
                if canonical == "" or canonical == "/":  # the static files' resource and the shell
                    path = "/style.css" if canonical == "" else "/"
                # POST /signin answers for the form it is sent: the next test's.
                methods = {route.method for route in resource} - {"HEAD"} - ({"POST"} if canonical == "/signin" else set())
                for method in methods:
                    for who, token in CREDENTIALS.items():
                        headers = {"Authorization": f"Bearer {token}"} if token else {}
                        async with http.request(method, url + path, headers=headers) as r:
                            got[(canonical, method, who)] = (declared[resource], r.status, await r.text())
            connects = {}
            for who, token in CREDENTIALS.items():
                sio = socketio.AsyncClient(reconnection=False)
                why: list = []
                sio.on("connect_error", why.append, namespace="/ui")
                try:
                    await sio.connect(url, headers={"Authorization": f"Bearer {token}"} if token else {},
                                      namespaces=["/ui"], transports=["websocket"], wait_timeout=5)
                    connects[who] = True
                    assert (await sio.call("subscribe", {"nodes": None}, namespace="/ui", timeout=5))["ok"]
                    await sio.disconnect()
                except socketio.exceptions.ConnectionError:
                    connects[who] = str(why)
            async with http.get(url + "/api/health", headers={"Authorization": f"Bearer {ADMIN}"}) as r:
                refused = (await r.json())["refused"]
    finally:
        await relay.stop()
    return got, connects, refused, undeclared, {r.canonical: a for r, a in declared.items()}


def test_every_route_and_ui_event_answers_each_role_as_the_policy_says(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    got, connects, refused, undeclared, declared = asyncio.run(_walk(tmp_path, caplog))
    assert undeclared == [], "routes whose action the policy does not know"
    assert {"/api/nodes", "/metrics", "/ingest", "/signin", "/signout", "/socket.io/", "/"} <= set(declared)
    wrong = {key: (action, status, text[:80]) for key, (action, status, text) in got.items()
             if _status_kind(status) != EXPECTED[action][key[2]]}
    assert wrong == {}
    # Every refusal says why, never with a credential.
    reasons = {text for action, status, text in got.values() if status in (401, 403)}
    assert any("a credential is required" in t for t in reasons) and any("wrong or expired" in t for t in reasons)
    assert any("viewer's credential may not stream" in t for t in reasons)
    assert any("node's credential may not read" in t for t in reasons)

    assert {who: ok is True for who, ok in connects.items()} == UI_CONNECTS
    assert "credential is required" in connects["none"] and "may not read" in connects["node"]
    assert {name[3:] for name in vars(UiNamespace) if name.startswith("on_")} == UI_EVENTS

    # Counted: every refusal of the walk and of the /ui connects, by reason.
    statuses = [(status, text) for _, status, text in got.values()]
    assert refused["credential_missing"] == sum("credential is required" in t for s, t in statuses) + 1
    assert refused["credential_wrong"] == sum("wrong or expired" in t for s, t in statuses) + 1
    assert refused["role"] == sum(s in (401, 403) and "may not" in t for s, t in statuses) + 1
    lines = [r.getMessage() for r in caplog.records]
    assert sum(line.startswith("access: ") for line in lines) == sum(refused[k] for k in
                                                                     ("credential_missing", "credential_wrong", "role"))
    # Nothing the relay logged at DEBUG holds a credential.
    assert not [line for line in lines if any(token in line for token in (ADMIN, VIEWER, NODE))]


def test_the_page_signs_in_with_a_cookie_and_never_keeps_a_token_in_its_address(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)

    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", credentials=Credentials(ADMIN, {"ann": VIEWER}, {"DCU-1": NODE}),
                                  clock_port=0))
        url = f"http://127.0.0.1:{relay.port}"
        out = {}
        try:
            # unsafe: aiohttp's jar keeps no cookie of an IP address otherwise (browsers do).
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
                async with http.get(f"{url}/?token={VIEWER}&open=DCU-1", allow_redirects=False) as r:
                    out["redirect"] = (r.status, r.headers["Location"], r.headers.get("Set-Cookie", ""))
                async with http.get(f"{url}/api/nodes") as r:
                    out["with cookie"] = r.status
                async with http.get(f"{url}/signin") as r:
                    out["who"] = await r.json()
                async with http.post(f"{url}/signout") as r:
                    out["signout"] = (r.status, r.headers.get("Set-Cookie", ""))
                async with http.get(f"{url}/api/nodes") as r:
                    out["signed out"] = r.status
                for name, token in (("node", NODE), ("wrong", "nope")):
                    async with http.post(f"{url}/signin", data={"token": token}) as r:
                        out[f"signin {name}"] = (r.status, (await r.json())["error"])
                async with http.post(f"{url}/signin", data={"token": VIEWER}, headers={"Origin": "http://evil.example"}) as r:
                    out["cross-site"] = r.status
                async with http.post(f"{url}/signin", data={"token": ADMIN}) as r:
                    out["signin admin"] = r.status
                async with http.get(f"{url}/signin") as r:
                    out["who admin"] = await r.json()
                async with http.get(f"{url}/?token=wrong", allow_redirects=False) as r:
                    out["wrong redirect"] = (r.status, r.headers["Location"], r.headers.get("Set-Cookie", ""))
                async with http.get(f"{url}/ingest") as r:  # with the admin's cookie
                    out["cookie at ingest"] = r.status
        finally:
            await relay.stop()
        return out

    out = asyncio.run(scenario())
    status, location, cookie = out["redirect"]
    assert (status, location) == (303, "/?open=DCU-1")
    assert VIEWER not in cookie and f"{COOKIE}=" in cookie
    assert all(attr in cookie for attr in ("HttpOnly", "SameSite=Strict", f"Max-Age={COOKIE_LIFETIME_S}", "Path=/"))
    assert "Secure" not in cookie  # plain HTTP here: request.secure is false
    assert out["with cookie"] == 200 and out["who"] == {"required": True, "principal": {"role": "viewer", "name": "ann"}}
    assert out["signout"][0] == 204 and 'dcuscope_session=""' in out["signout"][1]
    assert out["signed out"] == 401
    assert out["signin node"] == (403, "forbidden: a node's credential may not read")
    assert out["signin wrong"][0] == 401 and out["cross-site"] == 403
    assert out["signin admin"] == 204 and out["who admin"]["principal"] == {"role": "admin", "name": "admin"}
    assert out["wrong redirect"] == (303, "/", "")
    assert out["cookie at ingest"] == 401  # a page's cookie never streams
    session = cookie.split(";")[0].split("=", 1)[1]
    lines = [r.getMessage() for r in caplog.records]
    assert any("access: " in line for line in lines)
    assert not [line for line in lines if any(secret in line for secret in (ADMIN, VIEWER, NODE, session))]


def test_session_cookies_are_signed_by_the_credential_and_expire():
    one = Policy(Credentials(ADMIN, {"ann": VIEWER}, {"DCU-1": NODE}))
    cookie = one.cookie_for(Principal(Role.VIEWER, "ann"), now=1000.0)
    assert VIEWER not in cookie
    assert one.by_cookie(cookie, now=1000.0 + COOKIE_LIFETIME_S - 1) == Principal(Role.VIEWER, "ann")
    assert one.by_cookie(cookie, now=1000.0 + COOKIE_LIFETIME_S + 1) is None  # expired
    # Another relay with the same token files takes it; one whose viewer has another token does not.
    assert Policy(Credentials(None, {"ann": VIEWER})).by_cookie(cookie, now=1000.0) == Principal(Role.VIEWER, "ann")
    assert Policy(Credentials(None, {"ann": VIEWER + "x"})).by_cookie(cookie, now=1000.0) is None
    body, mac = cookie.split(".")
    forged = one.cookie_for(Principal(Role.ADMIN, "admin"), now=1000.0).split(".")[0] + "." + mac
    assert one.by_cookie(forged, now=1000.0) is None
    for junk in ("", ".", "a.b.c", "%%%.%%%", body + ".", 42):
        assert one.by_cookie(junk, now=1000.0) is None
    with pytest.raises(Exception, match="another credential has too"):
        Policy(Credentials(ADMIN, {"ann": ADMIN}))


def test_a_client_certificate_names_a_node():
    # The shape of ssl.SSLSocket.getpeercert() for a verified client certificate.
    cert = {"subject": ((("countryName", "DE"),), (("commonName", "DCU-7"),)),
            "issuer": ((("commonName", "dcuscope test CA"),),), "version": 3, "serialNumber": "01",
            "notBefore": "Jan  1 00:00:00 2026 GMT", "notAfter": "Jan  1 00:00:00 2027 GMT"}
    assert certificate_principal(cert) == Principal(Role.NODE, "DCU-7")
    with_san = dict(cert, subjectAltName=(("IP Address", "10.0.0.7"), ("DNS", "dcu-7.plant.example")))
    assert certificate_principal(with_san) == Principal(Role.NODE, "dcu-7.plant.example")
    assert certificate_principal(with_san).node == "dcu-7.plant.example"
    assert certificate_principal({}) is None and certificate_principal(None) is None
    assert certificate_principal({"subject": ((("organizationName", "x"),),)}) is None
    policy = Policy(Credentials(ADMIN))
    assert policy.decide(certificate_principal(cert), True, Action.INGEST) == Principal(Role.NODE, "DCU-7")
    assert policy.decide(certificate_principal(cert), True, Action.READ).status == 403


def test_an_open_relay_lets_anyone_read_but_a_node_credential_still_may_not():
    nodes_only = Policy(Credentials(nodes={"DCU-1": NODE}))
    assert nodes_only.reads_open and not nodes_only.ingest_open
    assert nodes_only.decide(None, False, Action.READ).role is Role.VIEWER
    assert nodes_only.decide(None, False, Action.INGEST).status == 401
    assert nodes_only.decide(nodes_only.by_token(NODE), True, Action.READ).status == 403
    viewers_only = Policy(Credentials(viewers={"ann": VIEWER}))
    assert not viewers_only.ingest_open and viewers_only.decide(None, False, Action.INGEST).status == 401
    demo = Policy()
    assert demo.decide(None, False, Action.READ).name == "" and demo.decide(None, True, Action.INGEST).name == ""


def test_a_relay_that_certifies_nodes_takes_the_certificates_name_and_no_token_against_it():
    policy = Policy(Credentials(ADMIN, {"ann": VIEWER}, {"DCU-1": NODE}), certified=True)
    cert = Principal(Role.NODE, "DCU-7")
    assert policy._certified(None, policy.by_token(ADMIN), True).count == "certificate_missing"
    assert policy._certified(cert, None, False) == cert  # the certificate alone is the credential
    assert policy._certified(cert, policy.by_token(ADMIN), True) == cert  # the admin's token: bound to the certificate
    assert policy._certified(cert, None, True).count == "credential_wrong"
    assert policy._certified(cert, policy.by_token(VIEWER), True).count == "role"
    other = policy._certified(cert, policy.by_token(NODE), True)
    assert other.status == 403 and "'DCU-7'" in other.reason and "'DCU-1'" in other.reason
