"""A relay started with --token: the page takes ?token= from its address for Socket.IO and the API."""

from __future__ import annotations

from tests.relay.helpers import wait_for
from tests.ui.helpers import RelayThread, sim_nodes

TOKEN = "tok-3f9a"


def test_page_uses_the_token_of_its_address(browser, tmp_path):
    relay = RelayThread(tmp_path / "relay.db", token=TOKEN)
    try:
        feeder = sim_nodes(relay.url, tmp_path, ["DCU-1"], frames=40, sources=2, fps=40, paced=False, token=TOKEN)
        feeder.wait(60)
        page = browser.new_page()
        try:
            # Without the token: refused, and the page says how to get in.
            page.goto(relay.url + "/")
            page.wait_for_selector("#banner:not([hidden])", timeout=30000)
            assert "?token=" in page.locator("#banner").inner_text()
            assert "unauthorized" in page.locator("#conn").inner_text()
            assert page.evaluate("window.dcuscope.debug().stores") == {}

            # With it: live socket, backfilled frames, statistics and the session list (HTTP API).
            page.goto(f"{relay.url}/?token={TOKEN}")
            d = wait_for(lambda: (lambda d: d if d["stores"].get("DCU-1", {}).get("size") == 80 else None)(
                page.evaluate("window.dcuscope.debug()")), 60, 0.2, "the node's 80 frames")
            assert d["transport"] == "socket.io" and page.locator("#banner").is_hidden()
            # Statistics arrived: a marked bottleneck, or the relay's reason that no stage saturates.
            page.wait_for_selector("#stats-body tr.bottleneck, #stats-body .bottleneck-reason", timeout=10000)
            page.wait_for_selector('#session-select option[value="1"]', state="attached", timeout=15000)
        finally:
            page.close()
    finally:
        relay.stop()
