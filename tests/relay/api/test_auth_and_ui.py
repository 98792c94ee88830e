"""--token refuses nodes, browsers and HTTP clients without it; /ui pushes are throttled and batched."""

from __future__ import annotations

import asyncio
import time

import pytest
import socketio

from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.relay.api.ui import DEFAULT_MAX_FRAMES
from dcuscope.relay.live.framepack import unpack_push
from dcuscope.relay.live.pairing import DEFAULT_PUSH_HZ
from tests.conftest import run_cli
from tests.relay.helpers import (RelayProcess, finish_node, get_json, http_status, load_node, start_node)

TOKEN = "s3cret-token"
VIEWER = "viewer-token-0123456789"


async def ui_connect(url: str, auth: dict | None, query: str = "",
                     headers: dict | None = None) -> tuple[socketio.AsyncClient, list]:
    sio = socketio.AsyncClient(reconnection=False)
    got: list = []
    for event in ("nodes", "frames", "stats"):
        unpacked = unpack_push if event == "frames" else (lambda data: data)
        sio.on(event, (lambda e, read: lambda data: got.append((time.monotonic(), e, read(data))))(event, unpacked),
               namespace="/ui")
    await sio.connect(url + query, auth=auth, headers=headers or {}, namespaces=["/ui"], transports=["websocket"],
                      wait_timeout=5)
    return sio, got


def test_token_refusals(tmp_path):
    viewers = tmp_path / "viewers"
    viewers.write_text(f"ann {VIEWER}\n")
    relay = RelayProcess(tmp_path / "relay.db", token=TOKEN, args=["--viewer-tokens", str(viewers)])
    try:
        # A node without the token, or with a viewer's, ships nothing and says why.
        for name, token in (("intruder", None), ("viewer", VIEWER)):
            bad = start_node(relay.url, name, tmp_path / f"{name}.npz", frames=20, fps=50, token=token,
                             extra=["--close-timeout", "2"])
            counters = finish_node(bad, 30, status=UNACKNOWLEDGED_STATUS)
            assert counters["acked"] == 0 and "refused the token" in counters["last_error"], name
        assert get_json(f"{relay.url}/api/health", VIEWER)["refused"]["role"] >= 1
        good = start_node(relay.url, "DCU-1", tmp_path / "good.npz", frames=20, fps=50, token=TOKEN)
        assert finish_node(good, 30)["acked"] > 0

        # HTTP: the header (or the page's cookie, tests/relay/guard/test_policy.py); a token in the address is none.
        assert http_status(f"{relay.url}/api/nodes") == 401
        assert http_status(f"{relay.url}/api/stats?node=DCU-1", {"Authorization": "Bearer wrong"}) == 401
        assert http_status(f"{relay.url}/api/nodes", {"Authorization": f"Bearer {TOKEN}"}) == 200
        assert http_status(f"{relay.url}/api/sessions?token={TOKEN}") == 401
        assert [n["node"] for n in get_json(f"{relay.url}/api/nodes", TOKEN)] == ["DCU-1"]

        async def browsers():
            for auth, query, headers in ((None, "", None), (None, "", {"Authorization": "Bearer wrong"}),
                                         ({"token": TOKEN}, f"?token={TOKEN}", None)):
                with pytest.raises(socketio.exceptions.ConnectionError):
                    await ui_connect(relay.url, auth, query, headers)
            for headers in ({"Authorization": f"Bearer {TOKEN}"},):
                sio, got = await ui_connect(relay.url, None, "", headers)
                for _ in range(50):
                    if got:
                        break
                    await asyncio.sleep(0.05)
                assert got and got[0][1] == "nodes" and got[0][2][0]["node"] == "DCU-1"
                await sio.disconnect()

        asyncio.run(browsers())
    finally:
        relay.stop()


def test_ui_pushes_frames_and_stats_throttled(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db")

    async def watch():
        sio, got = await ui_connect(relay.url, None)
        other, got_other = await ui_connect(relay.url, None)
        narrow, got_narrow = await ui_connect(relay.url, None)
        assert (await other.call("subscribe", {"nodes": ["elsewhere"]}, namespace="/ui")) == {"ok": True}
        assert (await narrow.call("subscribe", {"nodes": None, "max_frames": 1}, namespace="/ui")) == {"ok": True}
        bad = await narrow.call("subscribe", {"max_frames": 10**6}, namespace="/ui")
        assert bad["ok"] is False
        node = start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=150, sources=2, fps=50, paced=True)
        while node.poll() is None:
            await asyncio.sleep(0.1)
        # Statistics go once a second, after the frames, later on a loaded relay: the last ones counted
        # every frame, within a bound
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not [d for _, e, d in got if e == "stats"
                                                   and d["nodes"].get("DCU-1", {}).get("frames", {}).get("complete") == 300]:
            await asyncio.sleep(0.1)
        await asyncio.sleep(0.5)  # a frames push the other browsers get at the same tick
        for c in (sio, other, narrow):
            await c.disconnect()
        assert not [d for _, e, d in got_other if e == "frames"]
        narrow_frames = [d["nodes"]["DCU-1"] for _, e, d in got_narrow if e == "frames"]
        assert narrow_frames and all(len(b["frames"]) == 1 for b in narrow_frames)
        assert narrow_frames[-1]["cursor"] == 300 and narrow_frames[-1]["frames"][0]["n"] == 300
        return node, got

    try:
        node, got = asyncio.run(watch())
        counters = finish_node(node, 30)
        assert counters["acked"] == counters["events"]
        frames = [(t, d) for t, e, d in got if e == "frames"]
        stats = [d for _, e, d in got if e == "stats"]
        assert frames and stats
        times = [t for t, _ in frames]
        span = times[-1] - times[0]
        assert len(frames) <= DEFAULT_PUSH_HZ * span + 2  # at most push_hz pushes a second
        blocks = [d["nodes"]["DCU-1"] for _, d in frames]
        assert blocks[0]["kinds"] == {"src0": "framestamp", "src1": "framestamp", "mux": "mux", "infer": "infer",
                                      "tiler": "tiler", "convert": "convert", "osd": "osd", "sink": "fakesink"}
        pushed = [raw(f) for b in blocks for f in b["frames"]]
        cursors = [f["n"] for f in pushed]
        assert cursors == sorted(set(cursors)) and cursors[-1] == 300  # each frame once, in order, to the last
        # 100 frames a second at 30 pushes fit under the cap of 25 a push; a push that comes late on a
        # loaded machine holds the newest 25 of those completed since the one before, and its cursor tells the gap
        before = 0
        for b in blocks:
            since = b["cursor"] - before
            assert [raw(f)["n"] for f in b["frames"]] == list(range(b["cursor"] - min(since, DEFAULT_MAX_FRAMES) + 1, b["cursor"] + 1))
            before = b["cursor"]
        view = get_json(f"{relay.url}/api/frames?node=DCU-1&limit=2000")
        api = {(f["source"], f["frame"]): raw(f) for f in view["frames"]}
        for f in pushed:
            assert same_frame(api[(f["source"], f["frame"])], f), f
        header, _ = load_node(tmp_path / "n.npz")
        last = stats[-1]["nodes"]["DCU-1"]
        assert last["frames"]["complete"] == 300 and set(last["stages"]) == set(header.stages[2:-1])
        assert last["bottleneck"]["stage"] == "infer" and "window" in last
    finally:
        relay.stop()


def raw(frame: dict) -> dict:
    """A pushed frame with its clock correction undone (it changes as estimates improve): the
    frame's offset at its origin added back to its timestamps (a drift moves its other timestamps
    by a few ns more: see :func:`same_frame`), the correction's own fields left out."""
    back = frame["clock_ns"]
    def undo(values):
        return [None if v is None else v + back for v in values]
    out = {k: v for k, v in frame.items() if k not in ("clock_ns", "clock_uncertainty_ns", "glass_ms")}
    return dict(out, origin=frame["origin"] + back, end=frame["end"] + back, enter=undo(frame["enter"]),
                exit=undo(frame["exit"]))


def same_frame(a: dict, b: dict) -> bool:
    """Raw frames equal, their timestamps to within 1 µs (two estimates of a drift differ by ns)."""
    def close(x, y):
        return x is None and y is None or x is not None and y is not None and abs(x - y) <= 1000
    times = ("origin", "end", "enter", "exit")
    return ({k: v for k, v in a.items() if k not in times} == {k: v for k, v in b.items() if k not in times}
            and close(a["origin"], b["origin"]) and close(a["end"], b["end"])
            and all(map(close, a["enter"] + a["exit"], b["enter"] + b["exit"])))


def test_a_node_with_a_wrong_token_exits_non_zero_with_one_line(tmp_path):
    """``dcuscope run --probes --relay URL --token WRONG`` used to exit 0 having shipped nothing;
    a live run without limits now ends before it starts (without the check it runs for ever)."""
    config = tmp_path / "n.yaml"
    config.write_text("node: DCU-1\nsources:\n  - {test: ball, width: 160, height: 120, rate: 30}\n"
                      "stages:\n  - mux: {batch-size: 1, width: 160, height: 120}\n  - tiler: {rows: 1, columns: 1, width: 160, height: 120}\n"
                      "  - convert: {}\n")
    relay = RelayProcess(tmp_path / "relay.db", token=TOKEN)
    try:
        result = run_cli("run", config, "--probes", "--relay", relay.url, "--token", "WRONG", "-q", cwd=tmp_path,
                         timeout=120)
        assert get_json(f"{relay.url}/api/nodes", TOKEN) == []
    finally:
        relay.stop()
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [f"dcuscope: error: relay {relay.url} refused the token "
                                                   "(HTTP 401: unauthorized: wrong or expired credential)"]


def test_a_browser_may_subscribe_as_it_connects_and_a_malformed_wish_is_refused(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db")

    async def watch():
        for bad in ({"max_frames": 0}, {"nodes": "DCU-1"}, {"overview": "yes"}, ["DCU-1"]):
            with pytest.raises(socketio.exceptions.ConnectionError):
                await ui_connect(relay.url, {"subscribe": bad})
        shown, got_shown = await ui_connect(relay.url, {"subscribe": {"nodes": ["DCU-2"], "max_frames": 3}})
        node_1 = start_node(relay.url, "DCU-1", tmp_path / "1.npz", frames=100, sources=2, fps=50, paced=True)
        node_2 = start_node(relay.url, "DCU-2", tmp_path / "2.npz", frames=100, sources=2, fps=50, paced=True)
        while node_1.poll() is None or node_2.poll() is None:
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.5)
        await shown.disconnect()
        return [d for _, e, d in got_shown if e == "frames"], [d for _, e, d in got_shown if e == "stats"]

    try:
        frames, stats = asyncio.run(watch())
        assert frames and all(set(d["nodes"]) == {"DCU-2"} and len(d["nodes"]["DCU-2"]["frames"]) <= 3 for d in frames)
        assert stats and all(set(d["nodes"]) == {"DCU-2"} for d in stats)
    finally:
        relay.stop()
