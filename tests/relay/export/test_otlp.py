"""``dcuscope relay --otlp URL``: frames as OpenTelemetry traces, received by a real OTLP/HTTP receiver
on loopback (:mod:`tests.relay.otlpreceiver`, decoding with opentelemetry-proto).

Two real pipeline nodes feed a relay with ``--frame-limit 60 --otlp-every 10``: DCU-1 (clock
shifted by ``--clock-offset-ms 37``) has a slow ``identity`` behind a mux that drops frames older
than 80 ms, so that most of its frames take 80-105 ms, over the limit; DCU-2 is fast, all under it.
Each trace must be one frame the relay finalised, with the spans nested as documented, the
attributes set, every time and duration equal to what ``/api/frames`` shows for that frame,
and the set of traces exactly every 10th finalised frame of each node plus every frame over
the limit. A stalled receiver must cost frames (counted), never the ingest.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import urllib.request
from collections import defaultdict

import pytest
from prometheus_client.parser import text_string_to_metric_families

from dcuscope.cli import main as cli_main
from tests.conftest import cli_env
from tests.relay.helpers import RelayProcess, finish_node, get_json, start_node, wait_for
from tests.relay.otlpreceiver import OtlpReceiver

DURATION_S = 10
EVERY = 10
LIMIT_MS = 60
OFFSET_MS = 37
US = 1_000
SLOW = ("node: DCU-1\nsources:\n  - {test: smpte, width: 320, height: 240, rate: 50, live: true}\nstages:\n"
        "  - mux: {batch-size: 1, width: 320, height: 240, live-source: true, max-latency: 80}\n"
        "  - factory: identity\n    name: work\n    properties: {sleep-time: 25000}\n  - queue: {}\n")
FAST = ("node: DCU-2\nsources:\n  - {test: ball, width: 160, height: 120, rate: 30, live: true}\nstages:\n"
        "  - mux: {batch-size: 1, width: 160, height: 120, live-source: true}\n  - queue: {}\n")


def scrape(url: str) -> dict[tuple, float]:
    """/metrics' samples: (name, sorted labels) -> value."""
    with urllib.request.urlopen(f"{url}/metrics", timeout=10) as r:
        text = r.read().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value for f in text_string_to_metric_families(text)
            for s in f.samples}


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(received spans by trace, /api/frames per node, /api/nodes per node, the exporter's counters, receiver)
    once both nodes ran and the exporter sent everything queued."""
    tmp = tmp_path_factory.mktemp("otlp")
    with OtlpReceiver() as receiver:
        # gzip through the SDK's own variable: what a deployment would set.
        relay = RelayProcess(tmp / "relay.db", clock="estimate",
                             prefix=["env", "OTEL_EXPORTER_OTLP_TRACES_COMPRESSION=gzip"],
                             args=["--otlp", receiver.url, "--otlp-every", str(EVERY), "--frame-limit", str(LIMIT_MS)])
        nodes = []
        try:
            for name, config, offset in (("DCU-1", SLOW, OFFSET_MS), ("DCU-2", FAST, 0)):
                (tmp / f"{name}.yaml").write_text(config)
                cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(tmp / f"{name}.yaml"), "--probes", "--relay",
                       relay.url, "--duration", str(DURATION_S), "--clock-offset-ms", str(offset), "-q"]
                nodes.append(subprocess.Popen(cmd, cwd=tmp, env=cli_env(), stderr=subprocess.PIPE, text=True))
            for proc in nodes:
                _, err = proc.communicate(timeout=DURATION_S + 90)
                assert proc.returncode == 0, err
            # Nothing finalises once the nodes stopped: the exporter's figures then stand still.
            otlp = wait_for(lambda: (lambda o: o if o["queue_frames"] == 0 and o["frames_exported"] +
                                     sum(o["dropped"].values()) == sum(o["frames"].values()) else None)(
                get_json(f"{relay.url}/api/health")["otlp"]), 30, 0.2, "the export queue drained")
            otlp["metrics"] = scrape(relay.url)
            views = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
            frames = {name: get_json(f"{relay.url}/api/frames?node={name}&limit=2000") for name in views}
            traces = defaultdict(list)
            for span in receiver.spans:
                traces[span.trace_id].append(span)
            yield traces, frames, views, otlp, receiver
        finally:
            for proc in nodes:
                stop(proc)
            assert relay.stop() == 0


def finalised(block: dict, view: dict) -> list[dict]:
    """The frames the relay finalised, in the order it did: one source, a FIFO pipeline, so by frame number."""
    frames = sorted(block["frames"], key=lambda f: f["frame"])
    assert {f["source"] for f in frames} == {0} and len(frames) == view["frames"]["shown"]
    return frames[:view["frames"]["finalised"]]


def roots_by_frame(traces: dict) -> dict[tuple[str, int], list]:
    out = {}
    for spans in traces.values():
        root = [s for s in spans if not s.parent_id]
        assert len(root) == 1 and root[0].name == "frame", [s.name for s in spans]
        key = (root[0].attributes["dcuscope.node"], root[0].attributes["dcuscope.frame"])
        assert key not in out, f"frame {key} sent twice"
        out[key] = spans
    return out


def test_the_traces_are_every_nth_finalised_frame_plus_every_frame_over_the_limit(exported):
    traces, frames, views, otlp, receiver = exported
    sent = roots_by_frame(traces)
    over_total = 0
    for node, block in frames.items():
        done = finalised(block, views[node])
        over = {f["frame"] for f in done if f["delay_ms"] > LIMIT_MS}
        sampled = {f["frame"] for i, f in enumerate(done) if i % EVERY == 0}
        assert {frame for n, frame in sent if n == node} == over | sampled, node
        over_total += len(over)
    # Some frames, not all, over the limit: both reasons to send one are exercised.
    assert 0 < over_total < sum(v["frames"]["finalised"] for v in views.values())
    assert len(sent) >= 15 + over_total // 2
    assert otlp["frames"]["over_limit"] == over_total
    assert otlp["frames_exported"] == len(sent) and otlp["spans_exported"] == len(receiver.spans)
    assert otlp["dropped"] == {"queue_full": 0, "export_failed": 0}
    m = otlp["metrics"]
    assert m[("dcuscope_otlp_frames_total", (("why", "over_limit"),))] == over_total
    assert m[("dcuscope_otlp_frames_total", (("why", "sampled"),))] == len(sent) - over_total
    assert m[("dcuscope_otlp_spans_exported_total", ())] == len(receiver.spans)
    assert m[("dcuscope_otlp_frames_dropped_total", (("reason", "queue_full"),))] == 0
    assert m[("dcuscope_otlp_queue_frames", ())] == 0 == m[("dcuscope_relay_queue_depth", (("queue", "otlp"),))]
    assert m[("dcuscope_otlp_queue_capacity_frames", ())] == 2048
    assert receiver.requests == receiver.gzipped > 0 and not receiver.refused


def test_spans_nest_and_carry_the_frame_s_identity_and_clock(exported):
    traces, frames, views, _, _ = exported
    applied: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for (node, number), spans in roots_by_frame(traces).items():
        by_id = {s.span_id: s for s in spans}
        assert len(by_id) == len(spans)
        root = next(s for s in spans if not s.parent_id)
        f = next(f for f in frames[node]["frames"] if f["frame"] == number)
        a = root.attributes
        assert a["dcuscope.run"] == views[node]["run"] and a["dcuscope.frame"] == number
        assert a["dcuscope.source.id"] == 0
        assert a["dcuscope.source.uri"] == views[node]["sources"]["0"]
        assert a["dcuscope.over_limit"] == (f["delay_ms"] > LIMIT_MS)
        assert a["dcuscope.sampled_why"] == ("over_limit" if a["dcuscope.over_limit"] else "sampled")
        assert a["dcuscope.limit_ms"] == LIMIT_MS
        # The clock in force when the frame was sent: none before the run's first estimate (a loaded
        # machine may finalise a node's first frames before its first clock exchange), then the estimate.
        applied[node].append((number, a["dcuscope.clock.applied"]))
        if a["dcuscope.clock.applied"] == "none":
            assert a["dcuscope.clock.offset_ns"] == 0
        else:
            assert a["dcuscope.clock.applied"] == "estimate"
            assert abs(a["dcuscope.clock.offset_ns"] - (OFFSET_MS * 1_000_000 if node == "DCU-1" else 0)) < 1_000_000
            assert a["dcuscope.clock.uncertainty_ns"] > 0
        assert root.resource["service.name"] == "dcuscope-relay" and root.resource["service.instance.id"] == node
        for s in spans:
            assert s.start <= s.end
            if s is root:
                continue
            parent = by_id[s.parent_id]
            if s.name in ("wait", "service"):
                assert parent.name == f"stage {s.attributes['dcuscope.stage']}"
            else:
                assert parent is root and s.name.split()[0] in ("stage", "gap")
            if s.name.startswith("stage "):
                stage = s.attributes["dcuscope.stage"]
                assert s.attributes["dcuscope.stage.kind"] == frames[node]["kinds"][stage]
    for node, seen in applied.items():
        kinds = [kind for _, kind in sorted(seen)]
        first = kinds.index("estimate")  # ValueError: no frame of the node carried an estimate
        assert set(kinds[first:]) == {"estimate"} and kinds.count("estimate") > len(kinds) // 2, (node, kinds)


def test_span_times_and_durations_equal_the_relay_s_corrected_frames(exported):
    traces, frames, _, _, _ = exported
    compared = 0
    for (node, number), spans in roots_by_frame(traces).items():
        block = frames[node]
        f = next(f for f in block["frames"] if f["frame"] == number)
        root = next(s for s in spans if not s.parent_id)
        # The estimate in force at the frame's origin when it was sent; /api/frames asked later may
        # correct it by a refined one (microseconds; both true within their bounds). On the node's
        # own clock the times are the same to the nanosecond.
        offset = root.attributes["dcuscope.clock.offset_ns"]
        refined = f["clock_ns"] - offset
        assert abs(refined) <= root.attributes["dcuscope.clock.uncertainty_ns"] + f["clock_uncertainty_ns"]
        assert (root.start - refined, root.end - refined) == (f["origin"], f["end"])
        assert abs(root.end - root.start - f["delay_ms"] * 1e6) < US
        assert root.attributes["dcuscope.delay_ms"] == pytest.approx(f["delay_ms"], abs=1e-6)
        named = {s.name: s for s in spans}
        for i, stage in enumerate(block["stages"]):
            if f["stage_delay_ms"][i] is not None:
                s = named[f"stage {stage}"]
                assert (s.start - refined, s.end - refined) == (f["enter"][i], f["exit"][i])
                assert abs(s.end - s.start - f["stage_delay_ms"][i] * 1e6) < US
                if f["stage_service_ms"][i] is not None:
                    wait, service = [x for x in spans if x.parent_id == s.span_id and x.name in ("wait", "service")]
                    wait, service = sorted((wait, service), key=lambda x: x.name != "wait")
                    assert abs(wait.end - wait.start - f["stage_wait_ms"][i] * 1e6) < US
                    assert abs(service.end - service.start - f["stage_service_ms"][i] * 1e6) < US
                    assert wait.start == s.start and wait.end == service.start and service.end == s.end
            if f["stage_gap_ms"][i] is not None:
                gap = [s for s in spans if s.name.startswith("gap ") and s.name.endswith(f"->{stage}")]
                assert len(gap) == 1 and gap[0].end - refined == f["enter"][i]
                assert abs(gap[0].end - gap[0].start - f["stage_gap_ms"][i] * 1e6) < US
                compared += 1
    assert compared > 0


def test_a_stalled_backend_costs_counted_frames_never_the_ingest(tmp_path):
    with OtlpReceiver("stall") as receiver:
        relay = RelayProcess(tmp_path / "relay.db", args=["--otlp", receiver.url, "--otlp-every", "1", "--otlp-queue",
                                                          "16", "--otlp-timeout", "1"])
        try:
            node = start_node(relay.url, "DCU-1", tmp_path / "n.npz", frames=400, sources=2, fps=25)
            sent = finish_node(node)
            # The node's 2 x 400 frames span 16 s of its time: all but the last ~2 s finalise.
            stats = wait_for(lambda: (lambda s: s if s["frames"]["complete"] == 800 else None)(
                get_json(f"{relay.url}/api/stats?node=DCU-1")), 30, 0.2, "every frame in /api/stats")
            otlp = wait_for(lambda: (lambda o: o if o["dropped"]["export_failed"] else None)(
                get_json(f"{relay.url}/api/health")["otlp"]), 30, 0.2, "an export timed out")
            finalised = get_json(f"{relay.url}/api/nodes")[0]["frames"]["finalised"]
            metrics = scrape(relay.url)
        finally:
            code = relay.stop()
    assert code == 0 and sent["lost"] == 0 and sent["acked"] == sent["events"] and stats["frames"]["incomplete"] == 0
    assert otlp["queue_frames"] <= 16 and otlp["frames_exported"] == 0 and otlp["spans_exported"] == 0
    assert otlp["dropped"]["queue_full"] > 0
    # Every finalised frame was chosen (1 in 1): queued (then lost with the stalled exports) or dropped at once.
    assert sum(otlp["frames"].values()) + otlp["dropped"]["queue_full"] == finalised
    assert receiver.spans == []
    # Scraped after /api/health: an export may have timed out in between.
    assert metrics[("dcuscope_otlp_frames_dropped_total", (("reason", "queue_full"),))] == otlp["dropped"]["queue_full"]
    failed = metrics[("dcuscope_otlp_frames_dropped_total", (("reason", "export_failed"),))]
    assert failed >= otlp["dropped"]["export_failed"]
    assert metrics[("dcuscope_otlp_queue_capacity_frames", ())] == 16


@pytest.mark.parametrize("args, says", [
    (["--otlp", "ftp://collector:4318"], "give an OTLP/HTTP URL"),
    (["--otlp", "http://"], "give an OTLP/HTTP URL"),
    (["--otlp", "http://collector:99999"], "--otlp 'http://collector:99999': Port out of range"),
    (["--otlp", "http://c:4318", "--otlp-every", "-1"], "--otlp-every must be 0"),
    (["--otlp", "http://c:4318", "--otlp-every", "0"], "give a --frame-limit"),
    (["--otlp", "http://c:4318", "--otlp-queue", "0"], "--otlp-queue must be 1..1000000"),
    (["--otlp", "http://c:4318", "--otlp-timeout", "nan"], "--otlp-timeout must be over 0"),
    (["--otlp-every", "5"], "--otlp-every needs --otlp URL"),
])
def test_bad_otlp_options_get_a_one_line_error_and_exit_2(tmp_path, capsys, args, says):
    assert cli_main(["relay", "--port", "0", "--db", str(tmp_path / "r.db"), *args]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_non_number_is_refused_by_the_command_line_with_exit_2(tmp_path):
    out = subprocess.run([sys.executable, "-m", "dcuscope.cli", "relay", "--port", "0", "--db", str(tmp_path / "r.db"),
                          "--otlp", "http://c:4318", "--otlp-queue", "many"], capture_output=True, text=True,
                         timeout=60, env=cli_env())
    assert out.returncode == 2 and "--otlp-queue: invalid int value: 'many'" in out.stderr
