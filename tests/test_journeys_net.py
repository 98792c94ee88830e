"""A frame's journey across two DCUs on a real network: RTP from a sender namespace to a receiver
namespace over a veth pair and a delay line that holds every packet 20 ms (and, on one of the two
streams, drops a quarter of them), the receiver's clock off by a known amount
(``--clock-offset-ms``), one relay in the receiver's namespace aligning both.

Ground truth taken in the same run: the delay line's log of every packet (when it came, when it
left, or that it was dropped) and the receiver's offset. (The kernel here has no netem: see
tests/delayline.py.)"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from collections import defaultdict

import numpy as np
import pytest

from dcuscope.model.journeys import crossings, join
from dcuscope.protocol.events import RTP_IN, RTP_OUT
from dcuscope.relay.store.runs import load_runs
from tests.conftest import cli_env, run_cli
from tests.linkednet import RECEIVER_ADDR, LinkedNet, netns_permitted
from tests.relay.helpers import RelayProcess

pytestmark = pytest.mark.alone  # half a millisecond of truth: nothing else may run beside it

DELAY_MS, OFFSET_MS, LOSS = 20.0, 37.0, 0.25
LINE_PORT, PORT = 5700, 5600
SETTLE_MS = 0.5
"""What the issue allows beyond the clocks' stated error."""
H264 = ('x264enc tune=zerolatency speed-preset=ultrafast key-int-max=10 ! rtph264pay mtu=600 config-interval=-1 ! '
        'udpsink host={host} port={port} sync=false')
H264_IN = ('udpsrc address=127.0.0.1 port={port} '
           'caps="application/x-rtp,media=video,encoding-name=H264,clock-rate=90000,payload=96" '
           '! rtpjitterbuffer latency=200 ! rtph264depay ! avdec_h264 ! videoconvert ! fakesink')
JPEG = 'jpegenc quality=30 ! rtpjpegpay mtu=1400 ! udpsink host={host} port={port} sync=false'
JPEG_IN = ('udpsrc address=127.0.0.1 port={port} '
           'caps="application/x-rtp,media=video,encoding-name=JPEG,clock-rate=90000,payload=26" '
           '! rtpjpegdepay ! jpegdec ! fakesink')


def launch_config(tmp_path, node: str, line: str):
    path = tmp_path / f"{node}.yaml"
    path.write_text(f"node: {node}\nlaunch: >\n  {line}\n")
    return path


def source(width: int, height: int) -> str:
    return (f"videotestsrc is-live=true pattern=ball ! video/x-raw,format=I420,width={width},height={height},"
            f"framerate=25/1 ! ")


def rtp_key(ssrc: int, rtptime: int) -> int:
    """The link key of an RTP frame, as the tracer computes it (probes/capture/c/links.c)."""
    def mix(z: int) -> int:
        m = (1 << 64) - 1
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & m
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & m
        return z ^ (z >> 31)
    return mix(ssrc << 32 | rtptime) & ((1 << 44) - 1)


def line_frames(path) -> dict[int, dict]:
    """Per link key, from the delay line's log: its first packet's hold (ns) and whether any packet got through."""
    frames: dict[int, dict] = defaultdict(lambda: {"hold": None, "through": False})
    for line in path.read_text().splitlines():
        p = json.loads(line)
        f = frames[rtp_key(p["ssrc"], p["rtptime"])]
        if p["out"] is not None:
            f["through"] = True
            if f["hold"] is None:
                f["hold"] = p["out"] - p["in"]
    return dict(frames)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    why = netns_permitted()
    if why is not None:
        pytest.skip(why)
    tmp = tmp_path_factory.mktemp("journeys")
    with LinkedNet(tmp) as net:
        relay = RelayProcess(tmp / "relay.db", clock="estimate", args=["--host", RECEIVER_ADDR],
                             prefix=net.prefix(net.receiver))
        try:
            for i, loss in enumerate((0.0, LOSS)):
                net.spawn(net.receiver, [sys.executable, "-m", "tests.delayline", "--listen",
                                         f"{RECEIVER_ADDR}:{LINE_PORT + i}", "--to", f"127.0.0.1:{PORT + i}",
                                         "--delay-ms", f"{DELAY_MS:g}", "--loss", str(loss), "--seconds", "8",
                                         "--log", str(tmp / f"line{i}.jsonl")], f"line{i}", env=cli_env())
            run = [sys.executable, "-m", "dcuscope.cli", "run"]
            receivers = [
                net.spawn(net.receiver, [*run, str(launch_config(tmp, node, line.format(port=PORT + i))), "--probes",
                                         "--relay", relay.url, "--clock-offset-ms", f"{OFFSET_MS:g}", "--duration", "7.5",
                                         "-q"], node, env=cli_env())
                for i, (node, line) in enumerate((("DCU-2", H264_IN), ("DCU-4", JPEG_IN)))]
            time.sleep(2.0)  # the receivers and the lines listen before the first packet
            senders = [
                net.spawn(net.sender, [*run, str(launch_config(tmp, node, source(w, h) + line.format(
                    host=RECEIVER_ADDR, port=LINE_PORT + i))), "--probes", "--relay", relay.url, "--duration", "3.5",
                                       "-q"], node, env=cli_env())
                for i, (node, line, w, h) in enumerate((("DCU-1", H264, 160, 120), ("DCU-3", JPEG, 64, 48)))]
            for proc, node in zip(senders + receivers, ("DCU-1", "DCU-3", "DCU-2", "DCU-4")):
                assert proc.wait(90) == 0, net.log(node)
            live = {path: fetch(net, relay.url + path) for path in ("/api/journeys?limit=500", "/metrics")}
        finally:
            assert relay.stop() == 0
    return tmp, load_runs(tmp / "relay.db", 1), [line_frames(tmp / f"line{i}.jsonl") for i in range(2)], live


def fetch(net: LinkedNet, url: str) -> str:
    """GET ``url`` from inside the receiver's namespace, where the relay listens."""
    code = "import sys, urllib.request; sys.stdout.write(urllib.request.urlopen(sys.argv[1], timeout=20).read().decode())"
    done = subprocess.run([*net.prefix(net.receiver), sys.executable, "-c", code, url], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def hops_by_key(runs, sender: str, receiver: str) -> dict[int, int]:
    """Per link key, the hop the relay's clocks give: the receiver's arrival minus the sender's send."""
    of = {r.header.node: crossings(r.events) for r in runs}
    sent = {k: t for k, t in of[sender][of[sender]["kind"] == RTP_OUT][["key", "ts"]].tolist()}
    got = of[receiver][of[receiver]["kind"] == RTP_IN][["key", "ts"]].tolist()
    return {k: t - sent[k] for k, t in got if k in sent}


def test_the_hop_reads_the_links_delay_on_the_relays_clock(session):
    tmp, runs, lines, _ = session
    assert sorted(r.header.node for r in runs) == ["DCU-1", "DCU-2", "DCU-3", "DCU-4"]
    result = run_cli("stats", "--db", tmp / "relay.db", "--session", "1", "--json", cwd=tmp)
    assert result.returncode == 0, result.stderr
    hop = json.loads(result.stdout)["journeys"]["hops"]["net DCU-1 → DCU-2"]
    assert hop["count"] >= 50 and hop["lost"] == 0
    # The error bars of both nodes' clocks, added: the receiver's 37 ms are gone within them.
    assert hop["clock_error_ms"] is not None and hop["clock_error_ms"] < 5
    holds = [f["hold"] for f in lines[0].values()]
    assert abs(np.median(holds) / 1e6 - DELAY_MS) < 1.0  # the line held them about as long as told
    assert abs(hop["p50_ms"] - np.median(holds) / 1e6) <= hop["clock_error_ms"] + SETTLE_MS, hop
    # Frame by frame, against the line's hold of that frame's first packet.
    hops = hops_by_key(runs, "DCU-1", "DCU-2")
    error = np.array([hops[k] - lines[0][k]["hold"] for k in hops if k in lines[0]]) / 1e6
    assert len(error) == hop["count"]
    assert abs(np.median(error)) <= hop["clock_error_ms"] + SETTLE_MS, np.percentile(error, [5, 50, 95])


def test_each_journey_is_its_parts_from_the_senders_origin_to_the_receivers_end(session):
    _, runs, _, _ = session
    joined = join(runs)
    journeys = [j for j in joined.journeys if j.nodes == ["DCU-1", "DCU-2"]]
    assert len(journeys) >= 50 and not joined.ambiguous and not joined.untraced
    for j in journeys:
        assert [name for name, _ in j.parts] == ["DCU-1", "net DCU-1 → DCU-2", "DCU-2"]
        assert sum(ns for _, ns in j.parts) == j.total_ns
        assert j.parts[0][1] > 0 and j.parts[2][1] > 0
    hops = np.array([j.parts[1][1] for j in journeys]) / 1e6
    assert abs(np.median(hops) - DELAY_MS) <= joined.hops["net DCU-1 → DCU-2"].clock_error_ns / 1e6 + SETTLE_MS + 1.0


def test_frames_the_link_dropped_are_counted_lost_on_their_hop(session):
    _, runs, lines, _ = session
    hop = join(runs).hops["net DCU-3 → DCU-4"]
    truth = lines[1]
    lost = {k for k, f in truth.items() if not f["through"]}
    assert len(lost) >= 10 and hop.lost >= 5
    # Every frame is one packet here and the receiver listened throughout: each frame the line
    # dropped is counted lost on the hop, unless it was sent before the first frame (after the
    # last) the receiver got, where a loss cannot be told from a receiver not there yet.
    sender = crossings(next(r for r in runs if r.header.node == "DCU-3").events)
    sent = dict(sender[sender["kind"] == RTP_OUT][["key", "ts"]].tolist())
    first, last = min(hop.sent_ns), max(hop.sent_ns)
    inside = {k for k in lost if first <= sent[k] <= last}
    assert hop.lost == len(inside), (hop.lost, len(inside), len(lost))
    assert len(hop.delays_ns) == len(truth) - len(lost)


def test_the_relay_joins_them_live_for_the_page_and_metrics(session):
    tmp, runs, lines, live = session
    doc = json.loads(live["/api/journeys?limit=500"])
    hop = doc["hops"]["net DCU-1 → DCU-2"]
    stored = json.loads(run_cli("stats", "--db", tmp / "relay.db", "--session", "1", "--json", cwd=tmp).stdout)
    assert hop["count"] == stored["journeys"]["hops"]["net DCU-1 → DCU-2"]["count"]
    holds = [f["hold"] for f in lines[0].values()]
    assert abs(hop["p50_ms"] - np.median(holds) / 1e6) <= hop["clock_error_ms"] + SETTLE_MS, hop
    assert doc["hops"]["net DCU-3 → DCU-4"]["lost"] == stored["journeys"]["hops"]["net DCU-3 → DCU-4"]["lost"]
    frames = [f for f in doc["frames"] if f["nodes"] == ["DCU-1", "DCU-2"]]
    assert frames, doc["frames"][:2]
    for f in frames:  # the parts follow each other on the relay's clock, from the start to the end
        assert [p["kind"] for p in f["parts"]] == ["node", "hop", "node"]
        assert f["parts"][0]["at_ns"] == 0 and f["parts"][-1]["at_ns"] + f["parts"][-1]["ns"] == f["total_ns"]
        assert all(a["at_ns"] + a["ns"] == b["at_ns"] for a, b in zip(f["parts"], f["parts"][1:]))
        assert f["end_ns"] - f["start_ns"] == f["total_ns"]
    text = live["/metrics"]
    count = re.search(r'^dcuscope_hop_delay_seconds_count\{from="DCU-1",to="DCU-2",transport="net"\} (\S+)$', text, re.M)
    assert count and float(count.group(1)) == hop["count"]
    assert re.search(r'^dcuscope_hop_lost_frames_total\{from="DCU-3",to="DCU-4",transport="net"\} (\S+)$', text, re.M)
    assert 'dcuscope_journey_delay_seconds_count{path="DCU-1 → DCU-2"}' in text


def test_compare_gives_the_hop_and_the_journey_rows_of_their_own(session):
    tmp, runs, _, _ = session
    result = run_cli("compare", "session:1", "session:1", "--db", tmp / "relay.db", "--node", "DCU-2", "--json",
                     "--resamples", "200", cwd=tmp)
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    rows = {r["stage"]: r for r in doc["rows"]}
    hop = join(runs).hops["net DCU-1 → DCU-2"]
    assert rows["net DCU-1 → DCU-2"]["values"][0]["frames"] == len(hop.delays_ns)
    assert rows["journey DCU-1 → DCU-2"]["values"][0]["frames"] >= 50
    assert "net DCU-1 → DCU-2" not in doc["stages"]  # not a stage of the node's pipeline
    assert doc["verdicts"][1]["verdict"] == "no significant change"
