"""The page's Compare tab in Chromium: two stored runs of one DCU (gst-launch-1.0 traced and shipped
live by ``dcuscope trace --relay``; the second's identity sleeps 2 ms more), per-stage bars of both
side by side with the change, its interval and the verdict, the same as ``dcuscope compare``."""

from __future__ import annotations

import json

from relay.store.runs import list_sessions
from tests.conftest import run_cli
from tests.relay.helpers import get_json, http_status
from tests.ui.helpers import RelayThread
from tests.ui.test_browser import SHOTS

NODE = "DCU-3"


def shipped(relay: RelayThread, tmp_path, sleep_us: int) -> None:
    result = run_cli("trace", "--relay", relay.url, "--node", NODE, "-o", tmp_path / f"{sleep_us}.trace.jsonl", "-q",
                     "--", "gst-launch-1.0", "-q", "videotestsrc", "num-buffers=200", "!",
                     "video/x-raw,width=160,height=120", "!", "identity", "name=work", f"sleep-time={sleep_us}", "!",
                     "videoconvert", "!", "fakesink", cwd=tmp_path)
    assert result.returncode == 0, result.stderr


def test_two_runs_of_one_dcu_side_by_side_with_the_change_and_its_interval(browser, tmp_path):
    relay = RelayThread(tmp_path / "relay.db")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        shipped(relay, tmp_path, 2000)
        shipped(relay, tmp_path, 4000)
        sessions = list_sessions(tmp_path / "relay.db")
        assert len(sessions) == 2, sessions  # newest first
        page.goto(relay.url + "/")
        with page.expect_response(lambda r: "/api/compare?" in r.url) as answer:
            page.click(".tab[data-tab=compare]")
        assert answer.value.ok
        page.wait_for_selector(".cmp-row[data-stage=work]")
        # Defaults: NEW the newest run, BASE the one before it of the same DCU.
        assert page.input_value("#compare-new") == f"{sessions[0]['session']}|{NODE}"
        assert page.input_value("#compare-base") == f"{sessions[1]['session']}|{NODE}"
        stages = page.eval_on_selector_all(".cmp-row", "rs => rs.map(r => r.dataset.stage)")
        assert stages[-1] == "e2e" and "work" in stages
        assert page.input_value("#compare-figure") == "p99"  # of 200 frames: two values, too few to be sure of
        page.select_option("#compare-figure", "p50")
        work = page.locator(".cmp-row[data-stage=work] .cmp-change")
        assert "slower" in work.inner_text() and "verdict-slower" in work.get_attribute("class")
        assert "slower" in page.text_content(".compare-verdict")
        widths = page.eval_on_selector_all(".cmp-row[data-stage=work] .cmp-bar", "bs => bs.map(b => b.getBoundingClientRect().width)")
        assert 1.6 < widths[1] / widths[0] < 2.4, widths  # about 4 ms against 2 ms
        whisker = page.locator(".cmp-row[data-stage=work] .ci").bounding_box()
        bar = page.locator(".cmp-row[data-stage=work] .cmp-bar.new").bounding_box()
        assert whisker["x"] <= bar["x"] + bar["width"] <= whisker["x"] + whisker["width"] + 2  # NEW's value inside its interval

        # The page shows what the API says, which is `dcuscope compare`'s document for the same runs.
        doc = get_json(answer.value.url)
        result = run_cli("compare", "--db", tmp_path / "relay.db", f"session:{sessions[1]['session']}",
                         f"session:{sessions[0]['session']}", "--json")
        assert result.returncode == 0, result.stderr
        cli = json.loads(result.stdout)
        for a, b in zip(doc["rows"], cli["rows"]):
            assert (a["stage"], a["kind"], a["values"]) == (b["stage"], b["kind"], b["values"])
            assert a["changes"][1]["p50"]["verdict"] == b["changes"][1]["p50"]["verdict"]
        pct = doc["rows"][[r["stage"] for r in doc["rows"]].index("work")]["changes"][1]["p50"]
        assert f"{pct['pct']:+.1f} %" in work.inner_text()
        base, new = sessions[1]["session"], sessions[0]["session"]
        for query, status in ((f"base={base}&new={new}&new_node={NODE}", 400), (f"base=x&base_node={NODE}", 400),
                              (f"base=99&base_node={NODE}&new={new}&new_node={NODE}", 404),
                              (f"base={base}&base_node=NOPE&new={new}&new_node={NODE}", 404),
                              (f"base={base}&base_node={NODE}&new={new}&new_node={NODE}&noise=200", 400)):
            assert http_status(f"{relay.url}/api/compare?{query}") == status, query
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / "compare-view.png"), full_page=True)
    finally:
        page.close()
        relay.stop()
    assert not errors, errors
