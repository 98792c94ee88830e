"""A relay over HTTPS that asks for a credential: the page shows its sign-in form, signs in with a
session cookie (relay/guard/signin.py; Secure, HttpOnly, SameSite=Strict), never keeps a token in its
address (also when opened with ?token=), and signs out in one click. Screenshots at 1280x800, with the
page's address drawn above, go to build/screenshots (docs/signin.png and docs/signed-in.png are copies)."""

from __future__ import annotations

from dcuscope.relay.guard.tls import ServerTls
from tests.relay.helpers import wait_for
from tests.tlscerts import TestCA
from tests.ui.helpers import ROOT, RelayThread, screenshot_with_address, sim_nodes

TOKEN = "tok-3f9a-admin-0123"
VIEWER = "tok-viewer-0123456789"
SHOTS = ROOT / "build" / "screenshots"


def _frames(page, at_least: int) -> dict:
    return wait_for(lambda: (lambda d: d if d["stores"].get("DCU-1", {}).get("size", 0) >= at_least else None)(
        page.evaluate("window.dcuscope.debug()")), 60, 0.2, f"{at_least} frames of DCU-1")


def test_page_signs_in_with_its_form_and_keeps_no_token_in_its_address(browser, tmp_path):
    ca = TestCA(tmp_path)
    server = ca.issue("relay")
    relay = RelayThread(tmp_path / "relay.db", token=TOKEN, viewer_tokens={"ann": VIEWER},
                        tls=ServerTls(server.cert, server.key))
    assert relay.url.startswith("https://")
    # Paced, 2 sources at 25 fps for 40 s: still streaming when the signed-in page is shot.
    feeder = sim_nodes(relay.url, tmp_path, ["DCU-1"], frames=1000, sources=2, fps=25, paced=True, token=TOKEN,
                       extra=["--relay-ca", str(ca.cert)])
    SHOTS.mkdir(parents=True, exist_ok=True)
    # Chromium does not know the test's CA: the page is served over TLS all the same.
    context = browser.new_context(viewport={"width": 1280, "height": 800}, ignore_https_errors=True)
    page = context.new_page()
    said: list[str] = []  # what the page met, for a failure's message
    page.on("pageerror", lambda e: said.append(f"error: {e}"))
    page.on("console", lambda m: said.append(f"console {m.type}: {m.text}"))
    page.on("requestfailed", lambda r: said.append(f"failed: {r.method} {r.url} {r.failure}"))
    try:
        page.goto(relay.url + "/")
        try:
            page.wait_for_selector("#signin:not([hidden])", timeout=30000)
        except Exception as exc:
            raise AssertionError(f"no sign-in form; #conn says {page.locator('#conn').inner_text()!r}, "
                                 f"the relay refused {dict(relay.relay.guard.refused)}; the page met {said}") from exc
        assert page.locator("#signout").is_hidden()
        assert page.evaluate("window.dcuscope.debug().stores") == {}
        assert page.locator("#conn").inner_text() == "signed out"
        screenshot_with_address(page, SHOTS / "signin.png")
        shots = {"signin": page.url}

        page.fill("#signin-token", "not-the-token")
        page.click("#signin button[type=submit]")
        page.wait_for_function("document.querySelector('#signin-error').textContent.includes('wrong')", timeout=10000)

        page.fill("#signin-token", VIEWER)
        page.click("#signin button[type=submit]")
        page.wait_for_selector("#signout:not([hidden])", timeout=30000)
        d = _frames(page, 120)  # a view filled for the screenshot
        assert d["transport"] == "socket.io" and page.locator("#signin").is_hidden()
        assert "ann" in page.locator("#signout").get_attribute("title")
        page.wait_for_selector("#stats-body tr.bottleneck, #stats-body .bottleneck-reason", timeout=15000)
        screenshot_with_address(page, SHOTS / "signed-in.png")
        shots["signed-in"] = page.url
        assert all(url == relay.url + "/" for url in shots.values()), shots
        print("page.url of the screenshots:", shots)
        cookie, = context.cookies()
        assert cookie["secure"] and cookie["httpOnly"] and cookie["sameSite"] == "Strict", cookie
        assert VIEWER not in cookie["value"] and TOKEN not in cookie["value"], cookie

        # Signing out is one click, and the form is back.
        page.click("#signout")
        page.wait_for_selector("#signin:not([hidden])", timeout=30000)

        # An old bookmark with ?token=: signed in, and the token leaves the address (and the history).
        page.goto(f"{relay.url}/?token={TOKEN}&open=DCU-1")
        _frames(page, 10)
        assert TOKEN not in page.url and page.url.startswith(relay.url + "/?open=DCU-1"), page.url
        assert TOKEN not in page.evaluate("JSON.stringify([location.href, history.length, document.referrer])")
        page.wait_for_selector('#session-select option[value="1"]', state="attached", timeout=15000)
    finally:
        context.close()
        feeder.stop()
        relay.stop()


def test_an_unanswered_first_ask_is_asked_again_and_ends_at_the_sign_in_form(browser, tmp_path):
    # The relay served the page, but its first GET /signin never gets an answer (a connection lost
    # without a reset): the page asks again after ASK_TIMEOUT_MS, instead of waiting for ever with
    # neither form nor feed. (An ask that fails outright was never the trouble: the feed's refusal
    # shows the form.)
    relay = RelayThread(tmp_path / "relay.db", token=TOKEN)
    page = browser.new_page()
    asks: list[str] = []

    def hold_the_first(route):
        asks.append(route.request.method)
        if len(asks) > 1:
            route.continue_()  # the first is left without an answer

    page.route("**/signin", hold_the_first)
    try:
        page.goto(relay.url + "/")
        page.wait_for_selector("#signin:not([hidden])", timeout=30000)
        assert asks == ["GET", "GET"] and page.locator("#conn").inner_text() == "signed out"
    finally:
        page.close()
        relay.stop()
