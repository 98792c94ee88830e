"""A GStreamer application dcuscope did not build, live in the relay's page next to a ``dcuscope
run`` node: ``gst-launch-1.0`` under GST_TRACERS=dcuscope, its trace streamed by ``dcuscope ship``;
afterwards the same trace read by ``dcuscope stats`` and exported to Perfetto."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from dcuscope.probes.capture.native import build
from tests.conftest import run_cli
from tests.relay.helpers import get_json, kill_all, wait_for
from tests.ui.helpers import ROOT, RelayThread, env, pipeline_nodes

pytestmark = pytest.mark.long  # its tests share a module fixture: one group of 30 s or more, started first

FOREIGN = "CAM-9"
STAGES = ["src", "capsfilter0", "t", "qa", "sleepy", "sinka", "qb", "enc", "sinkb"]
BRANCHES = [("t", "qa"), ("qa", "sleepy"), ("sleepy", "sinka"), ("t", "qb"), ("qb", "enc"), ("enc", "sinkb")]
LAUNCH = ("videotestsrc name=src is-live=true num-buffers=450 ! video/x-raw,width=320,height=240,framerate=30/1 ! "
          "tee name=t t. ! queue name=qa ! identity name=sleepy sleep-time=8000 ! fakesink name=sinka "
          "t. ! queue name=qb ! x264enc name=enc tune=zerolatency speed-preset=ultrafast ! fakesink name=sinkb")


@pytest.fixture(scope="module")
def both(browser, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("foreign")
    relay = RelayThread(tmp / "relay.db")
    ours = pipeline_nodes(relay.url, tmp, ["DCU-1"], configs=("configs/vtest.yaml",), duration=25)
    trace = tmp / "cam9.trace.jsonl"
    genv = {k: v for k, v in os.environ.items() if not k.startswith("GST_")}
    genv.update(GST_PLUGIN_PATH=str(build().parent), GST_TRACERS=f"dcuscope(node={FOREIGN},trace={trace})")
    app = subprocess.Popen(["gst-launch-1.0", "-q", *LAUNCH.split()], env=genv, stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE)
    ship = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "ship", str(trace), "--relay", relay.url],
                            cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    page = browser.new_page(viewport={"width": 1400, "height": 1100})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(relay.url + "/")
        yield relay, page, trace, app, ship
        assert not errors, errors
    finally:
        page.close()
        kill_all((app, ship))
        ours.stop()
        relay.stop()


def test_a_foreign_pipeline_is_live_next_to_a_dcuscope_node(both):
    relay, page, trace, app, ship = both

    def bars():
        d = page.evaluate("window.dcuscope.debug()")
        b = d["stage"]["bars"]
        ready = all(b.get(FOREIGN, {}).get(s, 0) > 0 for s in ("qa", "sleepy", "qb", "enc")) and \
            sum(b.get("DCU-1", {}).values()) > 0
        return d if ready else None

    d = wait_for(bars, 90, 0.5, "stage bars of the foreign app and of DCU-1")
    rows = {r["node"] for r in d["stage"]["rows"] if r["source"] is None}
    assert {FOREIGN, "DCU-1"} <= rows
    nodes = wait_for(lambda: (n := {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")})
                     and n[FOREIGN]["clock"]["applied"] == "estimate" and n, 30, 0.5, "the foreign app's clock estimate")
    # Stages are numbered as they first carry a frame (upstream first among those found together).
    stages = nodes[FOREIGN]["stages"]
    assert sorted(stages) == sorted(STAGES) and stages[:3] == STAGES[:3]
    assert {(stages[a], stages[b]) for a, b in nodes[FOREIGN]["links"]} >= set(BRANCHES)
    assert nodes[FOREIGN]["kinds"]["sleepy"] == "identity" and nodes[FOREIGN]["lineage_unknown"] == []
    page.wait_for_selector(f'#nodes-body tr[data-node="{FOREIGN}"]', timeout=10_000)

    # The app ends (450 frames at 30/s); ship follows the trace to its end line and exits.
    assert app.wait(60) == 0, app.stderr.read().decode()
    out, err = ship.communicate(timeout=60)
    assert ship.returncode == 0, err.decode()
    assert "the trace is ended" in err.decode()
    result = run_cli("stats", trace, "--json")
    assert result.returncode == 0, result.stderr
    node = json.loads(result.stdout)["nodes"][FOREIGN]
    assert node["frames"] == {"complete": 450, "incomplete": 0}
    assert node["stages"]["sleepy"]["service"]["p50_ms"] >= 8.0
    # The relay holds the same frames and finds the same stage delays (clock corrections shift
    # both ends of a delay alike; its percentiles may be estimates, within percentile_error).
    live = wait_for(lambda: (s := get_json(f"{relay.url}/api/stats?node={FOREIGN}"))["frames"]["complete"] == 450 and s,
                    30, 0.5, "the relay's count of the foreign app's frames")
    for stage in ("qa", "sleepy", "qb", "enc"):
        ours, theirs = live["stages"][stage], node["stages"][stage]
        assert ours["count"] == theirs["count"] == 450, stage
        assert abs(ours["mean_ms"] - theirs["mean_ms"]) < 0.001, stage
        assert abs(ours["p50_ms"] - theirs["p50_ms"]) <= 0.001 + live["percentile_error"] * theirs["p50_ms"], stage
    out_file = trace.with_suffix(".perfetto.json")
    result = run_cli("export", trace, "--format", "perfetto", "-o", out_file)
    assert result.returncode == 0, result.stderr
    slices = {(e.get("name"), e.get("cat")) for e in json.loads(out_file.read_text())["traceEvents"]}
    assert {("service", "sleepy"), ("service", "enc"), ("wait", "qa")} <= slices


def test_the_page_says_where_frame_lineage_stops(browser, tmp_path):
    """gdppay serialises frames into new buffers without their metadata: the trace names it
    (lineage_unknown) and the page marks its row; gdpdepay's pictures are a new source."""
    relay = RelayThread(tmp_path / "relay.db")
    trace = tmp_path / "gdp.trace.jsonl"
    genv = {k: v for k, v in os.environ.items() if not k.startswith("GST_")}
    genv.update(GST_PLUGIN_PATH=str(build().parent), GST_TRACERS=f"dcuscope(node=GDP,trace={trace})")
    app = subprocess.run(["gst-launch-1.0", "-q", "videotestsrc", "num-buffers=60", "!",
                          "video/x-raw,width=160,height=120", "!", "gdppay", "!", "gdpdepay", "!", "videoconvert", "!",
                          "fakesink"], env=genv, capture_output=True, text=True, timeout=60)
    page = browser.new_page(viewport={"width": 1400, "height": 1100})
    said: list[str] = []
    page.on("pageerror", lambda e: said.append(str(e)))
    page.on("console", lambda m: m.type == "error" and said.append(m.text))
    try:
        assert app.returncode == 0, app.stderr
        ship = subprocess.run([sys.executable, "-m", "dcuscope.cli", "ship", str(trace), "--relay", relay.url,
                               "--settle", "0"], cwd=ROOT, env=env(), capture_output=True, text=True, timeout=60)
        assert ship.returncode == 0, ship.stderr
        node = next(n for n in get_json(f"{relay.url}/api/nodes") if n["node"] == "GDP")
        assert node["lineage_unknown"] == ["gdppay0"] and node["sources"] == {"0": "videotestsrc0", "1": "gdpdepay0"}
        page.goto(relay.url + "/")
        badge = page.locator('.stats-node[data-node="GDP"] tr[data-stage="gdppay0"] .badge.lineage')
        try:
            badge.wait_for(timeout=30_000)
        except PlaywrightTimeout:  # say what the page held instead
            held = page.evaluate("window.dcuscope ? (({stats, nodes, opened, subscription, transport}) => ({"
                                 "stats: Object.keys(stats), nodes: nodes.map((n) => [n.node, n.lineage_unknown]), "
                                 "opened, subscription, transport}))(window.dcuscope.debug()) "
                                 ": `no script: ${document.body.innerText.slice(0, 300)}`")
            raise AssertionError(f"no lineage badge on GDP's gdppay0 row; the page held {held}; "
                                 f"its errors: {said}") from None
        assert badge.inner_text() == "lineage stops" and "cannot be followed" in badge.get_attribute("title")
        assert page.locator('.stats-node[data-node="GDP"] .badge.lineage').count() == 1
    finally:
        page.close()
        relay.stop()
