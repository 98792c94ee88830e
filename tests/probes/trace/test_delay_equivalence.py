"""One delay model, every path: the same troubled runs through every way dcuscope reports delays.

Runs from ``tests/probes/synth.troubled_run`` (seeded: complete frames, frames dropped midway,
lost single events, duplicates, reordering, late copies) go through

- trace files -> ``dcuscope stats --json``, ``dcuscope export`` (csv, perfetto);
- the live engine in this process (``LiveRun``: whole run and window), fed in arrival order;
- a real relay (``python -m dcuscope.relay --clock ptp``: no clock correction, so timestamps stay as
  shipped) fed by real ``RelayExporter`` clients: ``/api/stats`` (run and window),
  ``/api/frames``, the stored-session API, and ``dcuscope stats --db --session`` and
  ``dcuscope export --db`` over its database.

Agreement is exact: JSON numbers compared with == (Python writes a float so that it reads back
to the same bit pattern); the CSV writes ms with 6 decimals (1 ns), so a CSV figure is
compared with another path's figure formatted that way.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass

import numpy as np
import pytest

from dcuscope.model.delays import frame_delays, node_stats
from dcuscope.model.frametable import frame_events, frame_table
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.trace.tracefile import write_trace
from dcuscope.protocol.events import FACT
from dcuscope.relay.live.run import LiveRun
from tests.probes.synth import run_commands, troubled_run
from tests.relay.helpers import RelayProcess, get_json, wait_for

SEEDS = (0, 1, 2)
STATS_KEYS = ("stages", "gaps", "frame", "glass", "bottleneck", "fps", "sources", "dropped", "frames")
WINDOW_KEYS = ("window_s", "end_ns", "stages", "gaps", "frame", "glass", "bottleneck", "fps", "sources", "frames")
BATCH = 97  # events per batch fed to the in-process engine: frames straddle batches


@dataclass
class World:
    runs: dict  # node -> (header, events, n_late, dropped)
    traces: list
    db: str
    session: int
    relay_stats: dict  # node -> /api/stats
    relay_frames: dict  # node -> /api/frames block
    relay_nodes: dict  # node -> /api/nodes entry
    stored_stats: dict  # node -> /api/sessions/ID/stats
    stored_frames: dict  # node -> every frame of /api/sessions/ID/frames


def _json(value):
    return json.loads(json.dumps(value))


def _ship(url: str, runs: dict) -> None:
    """Every run at once (one session), the late copies only once the relay finalised frames."""
    exporters = {node: RelayExporter(url, node) for node in runs}
    for node, (header, events, n_late, _) in runs.items():
        exporters[node].start(header)
        exporters[node].write(events[:len(events) - n_late])

    def finalised():
        nodes = {n["node"]: n for n in get_json(f"{url}/api/nodes")}
        return all(node in nodes and nodes[node]["frames"]["finalised"] > 0 for node in runs)

    wait_for(finalised, 60, what="frames finalised on the relay")
    for node, (_, events, n_late, dropped) in runs.items():
        exporters[node].write(events[len(events) - n_late:])
        exporters[node].close(dropped)


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> World:
    tmp = tmp_path_factory.mktemp("equivalence")
    runs = {f"rand-{seed}": troubled_run(seed, node=f"rand-{seed}") for seed in SEEDS}
    traces = []
    for node, (header, events, _, dropped) in runs.items():
        traces.append(str(tmp / f"{node}.trace"))
        write_trace(traces[-1], header, events, dropped)
    relay = RelayProcess(tmp / "relay.db", clock="ptp")
    try:
        _ship(relay.url, runs)
        wait_for(lambda: all(n["ended"] for n in get_json(f"{relay.url}/api/nodes")), 60, what="runs ended")
        api = relay.url + "/api"
        stats = {node: get_json(f"{api}/stats?node={node}") for node in runs}  # merges what is pending
        session = get_json(f"{api}/sessions")[0]["session"]
        yield World(
            runs=runs, traces=traces, db=str(tmp / "relay.db"), session=session, relay_stats=stats,
            relay_nodes={n["node"]: n for n in get_json(f"{api}/nodes")},
            relay_frames={node: get_json(f"{api}/frames?node={node}&limit=2000") for node in runs},
            stored_stats={node: get_json(f"{api}/sessions/{session}/stats?node={node}") for node in runs},
            stored_frames={node: get_json(f"{api}/sessions/{session}/frames?node={node}&limit=10000")
                           for node in runs},
        )
    finally:
        relay.stop()


def _cli_json(*argv) -> dict:
    rc, out, err = run_commands(*argv)
    assert (rc, err) == (0, ""), err
    return json.loads(out)


def _live(header, events) -> LiveRun:
    run = LiveRun(header)
    for i in range(0, len(events), BATCH):
        run.add(events[i:i + BATCH])
        run.maintain()
    return run


def _pick(doc: dict, keys) -> dict:
    return {k: doc[k] for k in keys}


def test_the_runs_hold_every_kind_of_trouble(world):
    for node, (header, events, n_late, _) in world.runs.items():
        st = node_stats(header, events)
        assert st["frames"]["incomplete"] > 10 and st["frames"]["complete"] > 100, node
        assert n_late > 0 and world.relay_nodes[node]["frames"]["late_events"] > 0, node
        assert world.relay_nodes[node]["frames"]["evicted"] > 0, node  # early incomplete frames aged out
        assert _live(header, events).late > 0, node


def test_statistics_of_the_whole_run_agree_exactly_on_every_path(world):
    from_traces = _cli_json("stats", *world.traces, "--json")["nodes"]
    from_db = _cli_json("stats", "--db", world.db, "--session", str(world.session), "--json")["nodes"]
    # A stored run says what was subtracted from its timestamps (--clock ptp: nothing, bound 0);
    # a trace file holds the node's own clock and says nothing.
    for node, st in from_db.items():
        clock = st.pop("clock")
        assert (clock["applied"], clock["correction_ns"], clock["uncertainty_ns"]) == ("ptp", 0, 0), node
        assert clock == world.stored_stats[node]["clock"], node
    assert from_db == from_traces
    for node, (header, events, _, dropped) in world.runs.items():
        expected = from_traces[node]
        assert expected == _json(node_stats(header, events, dropped))
        assert _pick(world.relay_stats[node], STATS_KEYS) == expected, node
        assert _pick(world.stored_stats[node], STATS_KEYS) == expected, node
        live = _live(header, events)
        assert _pick(_json(live.run_stats(dropped)), STATS_KEYS) == expected, node
        assert world.relay_stats[node]["percentile_error"] == 0.0


def test_window_statistics_agree_with_the_model_over_the_frames_in_the_window(world):
    for node, (header, events, _, _) in world.runs.items():
        window = world.relay_stats[node]["window"]
        # The window ends at the present on the node's clock, as the relay saw it when asked.
        assert window["end_ns"] >= int(events["ts"].max())
        live = _live(header, events).window_stats(window["end_ns"])
        assert _pick(_json(live), WINDOW_KEYS) == _pick(window, WINDOW_KEYS)
        # The model's own figures over the frames whose chain ended in the window_s before its end.
        fd = frame_delays(frame_table(header, events))
        cutoff = window["end_ns"] - int(window["window_s"] * 1e9)
        inside = fd.chains.complete & (fd.chains.end >= cutoff)
        assert 0 < inside.sum() < fd.chains.complete.sum()  # the window is not the whole run
        ids = set(zip(fd.table.source[inside].tolist(), fd.table.frame[inside].tolist()))
        mine = np.array([(s, f) in ids for s, f in zip(events["source"].tolist(), events["frame"].tolist())])
        mine |= events["point"] == FACT  # the run's facts (threads) hold for its window too
        expected = _json(node_stats(header, events[mine]))
        assert _pick(window, ("stages", "gaps", "frame", "bottleneck", "fps")) == \
            _pick(expected, ("stages", "gaps", "frame", "bottleneck", "fps"))
        assert window["frames"]["complete"] == expected["frames"]["complete"]
        assert window["frames"]["incomplete"] == _incomplete_seen_since(fd, events, cutoff)


def _incomplete_seen_since(fd, events, cutoff: int) -> int:
    """Incomplete frames whose newest event (drops and facts are not the frame's) is at or after ``cutoff``."""
    events = frame_events(events)
    t = fd.table
    row = np.searchsorted((t.source.astype(np.int64) << 40) | t.frame,
                          (events["source"].astype(np.int64) << 40) | events["frame"])
    last = np.full(len(t), -1, np.int64)
    np.maximum.at(last, row, events["ts"])
    return int((~fd.chains.complete & (last >= cutoff)).sum())


def _frames_by_id(frames: list[dict]) -> dict:
    return {(f["source"], f["frame"]): {k: v for k, v in f.items() if k != "n"} for f in frames}


def test_per_frame_json_is_the_same_live_and_stored(world):
    for node, (header, events, _, _) in world.runs.items():
        live, stored = world.relay_frames[node], world.stored_frames[node]
        assert live["correction_ns"] == 0 and live["has_exit"] == stored["has_exit"]
        assert _frames_by_id(live["frames"]) == _frames_by_id(stored["frames"])
        fd = frame_delays(frame_table(header, events))
        assert stored["total"] == len(stored["frames"]) == int(fd.chains.complete.sum())
        for f in stored["frames"]:
            assert f["complete"] and f["delay_ms"] == (f["end"] - f["origin"]) / 1e6


def _csv_cells(text: str) -> dict:
    rows = list(csv.DictReader(io.StringIO(text)))
    return {(r["node"], int(r["source"]), int(r["frame"]), r["stage"]): r for r in rows}


def _perfetto_cells(doc: dict) -> dict:
    """(node, source, frame, stage) -> args of its slice or instant (not of the wait and service
    parts nested in the slice, nor of capture slices)."""
    names = {e["pid"]: e["args"]["name"] for e in doc["traceEvents"] if e.get("name") == "process_name"}
    return {(names[e["pid"]], e["args"]["source"], e["args"]["frame"], e["cat"]): e["args"]
            for e in doc["traceEvents"] if e["ph"] in ("X", "i") and e["name"].startswith("frame ")}


def _perfetto_by_node(doc: dict) -> list[str]:
    """Every trace event with its process named by its node and flow ids left out, sorted."""
    names = {e["pid"]: e["args"]["name"] for e in doc["traceEvents"] if e.get("name") == "process_name"}
    return sorted(json.dumps({**{k: v for k, v in e.items() if k != "id"}, "pid": names[e["pid"]]}, sort_keys=True)
                  for e in doc["traceEvents"] if e.get("name") != "process_sort_index")


def _without_clock(doc: dict) -> dict:
    """A Perfetto document without its clock labels and the clock args of its frames."""
    events = [e for e in doc["traceEvents"] if e.get("name") != "process_labels"]
    for e in events:
        if "clock_ns" in e.get("args", {}):
            e["args"] = {k: v for k, v in e["args"].items() if k not in ("clock_ns", "clock_uncertainty_ns")}
    return dict(doc, traceEvents=events)


def _ms6(value) -> str:
    return "" if value is None else f"{value:.6f}"


def test_exports_agree_with_each_other_and_with_the_frames_the_relay_sends(world, tmp_path):
    out = {}
    for source, args in (("trace", world.traces), ("db", ["--db", world.db, "--session", str(world.session)])):
        for fmt in ("csv", "perfetto"):
            path = tmp_path / f"{source}.{fmt}"
            rc, _, err = run_commands("export", *args, "--format", fmt, "-o", str(path))
            assert (rc, err) == (0, "")
            out[source, fmt] = path.read_text()
    # Node for node the same (the database lists its runs in the order they connected), but for
    # the clock: a stored run's correction (--clock ptp: 0, bound 0), none in a trace file.
    db_csv, trace_csv = (out[source, "csv"].splitlines() for source in ("db", "trace"))
    assert [line.rsplit(",", 2)[1:] for line in db_csv[1:]] == [["0", "0"]] * (len(db_csv) - 1)
    assert [line.rsplit(",", 2)[1:] for line in trace_csv[1:]] == [["0", ""]] * (len(trace_csv) - 1)
    assert sorted(line.rsplit(",", 2)[0] for line in db_csv) == sorted(line.rsplit(",", 2)[0] for line in trace_csv)
    db_doc = json.loads(out["db", "perfetto"])
    assert set(db_doc["otherData"]["clock"]) == set(world.runs)
    assert all(c["uncertainty_ns"] == 0 and c["applied"] == "ptp" for c in db_doc["otherData"]["clock"].values())
    assert _perfetto_by_node(_without_clock(db_doc)) == _perfetto_by_node(json.loads(out["trace", "perfetto"]))
    cells, slices = _csv_cells(out["trace", "csv"]), _perfetto_cells(json.loads(out["trace", "perfetto"]))
    assert cells.keys() == slices.keys()
    for key, row in cells.items():  # every frame, complete or not
        args = slices[key]
        assert row["complete"] == str(int(args["complete"])), key
        for figure in ("delay_ms", "gap_ms", "service_ms", "wait_ms"):
            assert row[figure] == _ms6(args.get(figure)), (key, figure)
    for node, (header, _, _, _) in world.runs.items():
        complete = {k[1:3] for k, r in cells.items() if k[0] == node and r["complete"] == "1"}
        frames = world.stored_frames[node]["frames"]
        assert {(f["source"], f["frame"]) for f in frames} == complete
        for f in frames:
            for s, stage in enumerate(header.stages):
                key = (node, f["source"], f["frame"], stage)
                if key not in cells:  # a stage the frame did not pass
                    assert f["stage_delay_ms"][s] is None and f["stage_gap_ms"][s] is None
                    continue
                assert slices[key].get("delay_ms") == f["stage_delay_ms"][s], key
                assert slices[key].get("gap_ms") == f["stage_gap_ms"][s], key
                assert cells[key]["delay_ms"] == _ms6(f["stage_delay_ms"][s]), key


@pytest.mark.parametrize("argv, message", [
    (["--db", "{tmp}/missing.db", "--session", "1"], "no such database"),
    (["--db", "{db}", "--session", "99"], "no session or run '99'"),
    (["--db", "{trace}", "--session", "1"], "not a usable relay database"),
    (["--db", "{db}"], "--db PATH with --session ID"),
    (["{trace}", "--db", "{db}", "--session", "1"], "--db PATH with --session ID"),
    ([], "give at least one TRACE file"),
])
def test_stats_from_a_database_refuses_bad_input_with_one_line(world, tmp_path, argv, message):
    argv = [a.format(tmp=tmp_path, db=world.db, trace=world.traces[0]) for a in argv]
    rc, out, err = run_commands("stats", *argv)
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert err.startswith("dcuscope: error: ") and message in err, err


def test_stats_table_from_a_database_is_the_table_of_the_trace_files(world):
    rc, from_db, _ = run_commands("stats", "--db", world.db, "--session", str(world.session))
    assert rc == 0
    rc, from_traces, _ = run_commands("stats", *world.traces)
    strip = [b.split("\n", 1)[1] for b in from_traces.strip().split("\n\n")]  # titles name the trace files
    by_node = {b.split("\n", 1)[0].split()[1]: b.split("\n", 1)[1] for b in from_db.strip().split("\n\n")}
    # A stored run's block ends with its clock: what was subtracted and its bound.
    clock = {node: block.rsplit("\n", 1)[1] for node, block in by_node.items()}
    assert all(line == "  clock          ptp: 0.0 µs subtracted ± 0.0 µs (--clock ptp)" for line in clock.values()), clock
    by_node = {node: block.rsplit("\n", 1)[0] for node, block in by_node.items()}
    assert sorted(by_node.values()) == sorted(strip) and set(by_node) == set(world.runs)
