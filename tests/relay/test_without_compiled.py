"""A relay without its compiled core (no compiler, or ``DCUSCOPE_COMPILED=0``) works as with it: the
numpy reference decodes, pairs, judges and pushes, the statistics are node_stats of what the nodes sent,
and its log says why once."""

from __future__ import annotations

from dcuscope.model.delays import node_stats
from tests.relay.helpers import RelayProcess, assert_stats_equal, finish_node, get_json, load_node, start_node


def test_a_relay_without_its_compiled_core_says_so_once_and_gives_the_same_statistics(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate", prefix=["env", "DCUSCOPE_COMPILED=0"])
    try:
        nodes = [start_node(relay.url, f"DCU-{k}", tmp_path / f"n{k}.npz", frames=150, sources=2, fps=60, paced=True,
                            drop_rate=0.05, seed=k) for k in (1, 2)]
        for k, proc in enumerate(nodes, 1):
            counters = finish_node(proc, 60)
            assert counters["acked"] == counters["events"], counters
            header, events = load_node(tmp_path / f"n{k}.npz")
            stats = get_json(f"{relay.url}/api/stats?node=DCU-{k}")
            assert_stats_equal(node_stats(header, events), stats)
            frames = get_json(f"{relay.url}/api/frames?node=DCU-{k}&since=0&limit=20")["frames"]
            assert len(frames) == 20 and all(f["complete"] for f in frames)
    finally:
        relay.stop()
    said = [line for line in relay.log.read_text().splitlines() if "compiled core unavailable" in line]
    assert len(said) == 1 and "switched off (DCUSCOPE_COMPILED=0)" in said[0], said
