"""dcuscope's elements in ``gst-launch-1.0`` through gst-python's plugin loader, several processes at once.

gst-python's loader keeps a borrowed pointer to ``sys.path`` while it imports our loader modules,
and ``import cv2`` replaced that list: the loader then wrote into freed memory, and gst-launch
processes with mux and infer died later with SIGSEGV in the Python allocator (seen 3 in 3 with
three processes on a loaded machine, 97 in 97 in one 3-minute spell here). See plugins.loading.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dcuscope.plugins.loading import same_sys_path
from dcuscope.probes.capture.native import build
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import ENTER, EXIT
from tests.conftest import REPO
from tests.probes.capture.test_gsttracer import frames_of, loader_env, stage_points

PROCESSES = 4
ROUNDS = 2
FRAMES = 6
# Two cameras of another size than the batch's (the mux scales), framestamp, infer, both in batches of 2.
# The shipped SSD: the crash was the loader's, whatever the model; it takes half CenterNet's CPU.
CHAIN = ("mux name=m batch-size=2 width=640 height=360 ! "
         f"infer name=infer threads=1 model={REPO / 'assets' / 'models' / 'ssdlite_mobilenetv2_person.onnx'} ! "
         "fakesink name=sink "
         f"videotestsrc num-buffers={FRAMES} ! video/x-raw,format=RGB,width=320,height=240 ! framestamp ! m.sink_0 "
         f"videotestsrc num-buffers={FRAMES} pattern=ball ! video/x-raw,format=RGB,width=320,height=240 ! "
         "framestamp source-id=1 ! m.sink_1")

PROBE_MODULE = '''
from dcuscope.core.gst import GObject, Gst, GstBase


class Probe(GstBase.BaseTransform):
    __gtype_name__ = "DcuscopeTestLoaderProbe"
    __gstmetadata__ = ("Loader probe", "Filter", "A Python element from a later plugin folder", "tests")
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, Gst.Caps.new_any()),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, Gst.Caps.new_any()),
    )


GObject.type_register(Probe)
__gstelementfactory__ = ("dcuscopetestloaderprobe", Gst.Rank.NONE, Probe)
'''


@pytest.fixture(scope="module")
def plugin_dir() -> Path:
    return build().parent


def exit_text(code: int) -> str:
    return f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit {code}"


def test_same_sys_path_keeps_the_list_object_and_takes_the_new_contents():
    before = sys.path
    saved = list(before)
    try:
        with same_sys_path():
            sys.path = [*before, "/nowhere/dcuscope-test"]  # what cv2's bootstrap does, with a copy
        assert sys.path is before and sys.path[-1] == "/nowhere/dcuscope-test"
    finally:
        before[:] = saved
        sys.path = before


def test_a_python_plugin_folder_after_ours_still_loads(plugin_dir, tmp_path):
    """The loader puts each GST_PLUGIN_PATH folder's ``python`` into the list it holds before it
    imports that folder's files: when our files had replaced ``sys.path``, a folder after ours went
    into the dead list and its module was not found (and the loader wrote into freed memory)."""
    more = tmp_path / "more"
    (more / "python").mkdir(parents=True)
    (more / "python" / "dcuscope_test_loader_probe.py").write_text(PROBE_MODULE)
    env = loader_env(plugin_dir, tmp_path, f"node=PROBE,trace={tmp_path / 'probe.jsonl'}")
    env["GST_PLUGIN_PATH"] = f"{REPO / 'plugins' / 'loader'}:{more}"
    for factory in ("mux", "dcuscopetestloaderprobe"):
        result = subprocess.run(["gst-inspect-1.0", factory], env=env, capture_output=True, text=True, timeout=180)
        assert result.returncode == 0, f"{factory}: {exit_text(result.returncode)}\n{result.stdout[-1000:]}{result.stderr}"


def test_four_gst_launch_processes_at_once_all_finish_with_their_frames(plugin_dir, tmp_path):
    """Four gst-launch processes of a traced mux + infer chain at once, three times: each exits 0 and
    every frame of both its cameras went through infer to the sink."""
    expected = {(source, frame) for source in (0, 1) for frame in range(FRAMES)}
    traces = [tmp_path / f"p{i}.jsonl" for i in range(PROCESSES)]
    envs = [loader_env(plugin_dir, tmp_path, f"node=P{i},trace={trace}") for i, trace in enumerate(traces)]
    # One registry for all four, made before they start (four first scans at once are not this test).
    warm = subprocess.run(["gst-inspect-1.0", "infer"], env=envs[0], capture_output=True, text=True, timeout=180)
    assert warm.returncode == 0, warm.stderr
    for round_ in range(ROUNDS):
        procs = [subprocess.Popen(["gst-launch-1.0", "--no-fault", *CHAIN.split()], env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True) for env in envs]
        try:
            outputs = [proc.communicate(timeout=240)[0] for proc in procs]
        finally:
            for proc in procs:
                proc.kill()
        for i, (proc, output) in enumerate(zip(procs, outputs)):
            assert proc.returncode == 0, f"round {round_}, process {i}: {exit_text(proc.returncode)}\n{output[-3000:]}"
            trace = read_trace(traces[i])
            assert frames_of(stage_points(trace, "infer", EXIT)) == expected, f"round {round_}, process {i}"
            assert frames_of(stage_points(trace, "sink", ENTER)) == expected, f"round {round_}, process {i}"
