"""``pip install`` gives a working tool: the wheel built from the checkout, installed into a fresh
venv (Debian's PyGObject beside it, as the README says), used from a folder outside the checkout.
First without extras, the tracing side of a DCU (its tracer, a gst-launch-1.0 app traced and shipped
to a relay, one import name, `run` naming the extra it lacks); then with [pipeline]: a pipeline whose
default model detects, and the demo."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import zipfile
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.dcuscope.test_demo import FIVE, get, statuses
from tests.ports import free_port

pytestmark = pytest.mark.long

SYSTEM_PYTHON = "/usr/bin/python3"  # Debian's: its python3-gi is the PyGObject dcuscope runs with
GST_LAUNCH = ["gst-launch-1.0", "-q", "videotestsrc", "num-buffers=40", "!", "video/x-raw,width=320,height=240", "!",
              "queue", "!", "videoconvert", "!", "fakesink"]


def pip_cache() -> str:
    """The user's pip cache (the checkout's setup filled it): the install reads it, HOME is elsewhere."""
    out = subprocess.run([sys.executable, "-m", "pip", "cache", "dir"], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else str(Path.home() / ".cache" / "pip")


def pip(venv: Path, env: dict, *args: str) -> float:
    """``pip install`` into ``venv`` with the tested versions; the seconds it took."""
    started = time.monotonic()
    done = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "--no-compile", "-c", str(REPO / "constraints.txt"),
                           *args], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return time.monotonic() - started


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv, a clean environment for it, its HOME, the wheel, a folder outside the checkout): the wheel
    built once and installed without extras, the tracing side a DCU needs (docs/on-a-dcu.md)."""
    tmp = tmp_path_factory.mktemp("wheel")
    home = tmp / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("GST_", "PYTHON", "VIRTUAL_ENV", "PIP_", "XDG_"))}
    env.update(HOME=str(home), PIP_CACHE_DIR=pip_cache(), PIP_DISABLE_PIP_VERSION_CHECK="1")
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(REPO)],
                           env=env, capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    (wheel,) = (tmp / "dist").glob("dcuscope-*.whl")
    venv = tmp / "venv"
    made = subprocess.run([SYSTEM_PYTHON, "-m", "venv", "--system-site-packages", str(venv)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    took = pip(venv, env, str(wheel))
    print(f"\nthe tracing side (no extras) installed in {took:.1f} s")
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env['PATH']}"
    outside = tmp / "work"
    outside.mkdir()
    return venv, env, home, wheel, outside


@pytest.fixture(scope="module")
def pipeline(installed):
    """The same venv with the [pipeline] extra added (OpenCV, ONNX Runtime): everything."""
    venv, env, _, wheel, _ = installed
    took = pip(venv, env, f"{wheel}[pipeline]")
    print(f"\nthe [pipeline] extra installed in {took:.1f} s")
    return installed


def dcuscope(installed, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    venv, env, _, _, outside = installed
    return subprocess.run([str(venv / "bin" / "dcuscope"), *args], cwd=outside, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_the_wheel_holds_one_package_with_its_native_sources_models_and_configs(installed):
    _, _, _, wheel, _ = installed
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"dcuscope"}, tops
    assert wheel.name.endswith("-py3-none-linux_x86_64.whl")  # a shared library inside: one per platform
    for part in ("probes/capture/c/tracer.c", "probes/capture/_build/libgstdcuscope.so", "model/c/merge.c", "model/c/judge.c", "model/c/core.h",
                 "model/_build/libdcuscope_core.so",
                 "assets/models/centernet_mobilenetv3_coco80.onnx", "assets/models/README.md",
                 "assets/models/ssdlite_mobilenetv2_person.onnx", "configs/vtest.yaml", "ui/static/index.html",
                 "ui/static/vendor/socket.io.min.js", "plugins/loader/python/dcuscope_infer.py"):
        assert f"dcuscope/{part}" in names, part
    assert not [n for n in names if "__pycache__" in n or "/tests/" in n]
    metadata = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "Requires-Python: >=3.10" in metadata
    assert "Provides-Extra: pipeline" in metadata and 'onnxruntime>=1.16; extra == "pipeline"' in metadata


def test_without_extras_a_dcu_traces_and_ships_and_run_names_the_extra(installed):
    """The tracing side alone (no OpenCV, no ONNX Runtime): an unchanged app traced and shipped live to a
    relay of the same install, which stores every event; `dcuscope run` says which extra it needs."""
    venv, env, home, _, outside = installed
    for module in ("cv2", "onnxruntime"):
        absent = subprocess.run([str(venv / "bin" / "python"), "-c", f"import {module}"], env=env, capture_output=True)
        assert absent.returncode != 0, f"{module} is installed without the [pipeline] extra"
    # One import name: dcuscope, and none of the folders' names.
    probe = subprocess.run([str(venv / "bin" / "python"), "-c", "import importlib.util as u, dcuscope, json; print(json.dumps("
                            "[dcuscope.__file__, [n for n in ('core', 'plugins', 'pipeline', 'probes', 'relay', 'ui') "
                            "if u.find_spec(n)]]))"], cwd=outside, env=env, capture_output=True, text=True, timeout=60)
    assert probe.returncode == 0, probe.stderr
    where, stray = json.loads(probe.stdout)
    assert Path(where).is_relative_to(venv) and stray == []

    found = dcuscope(installed, "plugin-path")
    assert found.returncode == 0, found.stderr
    assert Path(found.stdout.strip()).is_relative_to(venv) and (Path(found.stdout.strip()) / "libgstdcuscope.so").is_file()
    merge = subprocess.run([str(venv / "bin" / "python"), "-m", "dcuscope.model.compiled", "check"], cwd=outside, env=env,
                           capture_output=True, text=True, timeout=60)
    assert merge.returncode == 0 and Path(merge.stdout.split(": ", 1)[1].strip()).is_relative_to(venv), merge

    port = free_port()
    relay = subprocess.Popen([str(venv / "bin" / "dcuscope"), "relay", "--port", str(port), "--clock-port", "0",
                              "--db", "relay.db"], cwd=outside, env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                get(f"http://127.0.0.1:{port}/api/health")
                break
            except OSError:
                time.sleep(0.3)
        traced = dcuscope(installed, "trace", "--node", "CAM-1", "-o", "cam.trace.jsonl", "--quiet",
                          "--relay", f"http://127.0.0.1:{port}", "--", *GST_LAUNCH)
        assert traced.returncode == 0, traced.stderr
        stats = dcuscope(installed, "stats", "cam.trace.jsonl", "--json")
        assert stats.returncode == 0, stats.stderr
        node = json.loads(stats.stdout)["nodes"]["CAM-1"]
        assert node["frames"] == {"complete": 40, "incomplete": 0} and {"queue0", "videoconvert0"} <= set(node["stages"])
    finally:
        relay.terminate()
        relay.wait(30)
    listed = dcuscope(installed, "sessions", "--db", "relay.db", "--json")
    assert listed.returncode == 0, listed.stderr
    (run,) = [r for s in json.loads(listed.stdout) for r in s["runs"] if r["node"] == "CAM-1"]
    sent = json.loads((outside / "cam.trace.jsonl").read_text().splitlines()[-1])["end"]["events"]
    assert run["events"] == sent > 0 and run["state"] == "ended" and run["lost"] == 0, (run, sent)

    ran = dcuscope(installed, "run", "vtest", "--num-frames", "10")
    assert ran.returncode == 2 and len(ran.stderr.splitlines()) == 1, ran.stderr
    assert "needs opencv-python-headless and onnxruntime" in ran.stderr
    assert "pip install 'dcuscope[pipeline]'" in ran.stderr
    # The trace (nothing else) in the working folder, beside the relay's store.
    assert sorted(p.name for p in outside.iterdir() if not p.name.startswith("relay.db")) == ["cam.trace.jsonl"]


def test_with_the_pipeline_extra_the_default_model_detects(pipeline):
    venv, env, home, _, outside = pipeline
    ran = dcuscope(pipeline, "run", "vtest", "--num-frames", "10", timeout=240)  # a shipped config, by name
    assert ran.returncode == 0, ran.stderr
    (line,) = [x for x in ran.stderr.splitlines() if x.startswith("infer: ")]
    objects, frames = int(line.split()[1]), int(line.split()[4])
    assert objects > 0 and frames >= 10 and "person" in line, line

    # Nothing written outside the venv but GStreamer's own registry (any GStreamer application writes it);
    # ONNX Runtime's telemetry (a device id in ~/.cache) is off. Of the install, only pip's own: it runs
    # `rustc --version` for its user agent, and rustup writes its settings.
    written = sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())
    assert all(w.startswith((".cache/gstreamer-1.0/registry.", ".rustup/")) for w in written), written


def test_the_installed_demo_runs_two_dcus_that_report_all_five_stages_on_its_page(pipeline):
    """``dcuscope demo`` as the README gives it: the page and its vendored front-end served, both
    DCUs report every stage through the relay's API with a verdict each, and Ctrl-C stops it."""
    venv, env, _, _, outside = pipeline
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    demo = subprocess.Popen([str(venv / "bin" / "dcuscope"), "demo", "--port", str(port), "--duration", "150",
                             "--db", "demo.db"], cwd=outside, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)  # --duration: a bound only, Ctrl-C ends it
    lines: list[str] = []
    reader = threading.Thread(target=lambda: [lines.append(line) for line in demo.stdout], daemon=True)
    reader.start()
    try:
        seen: dict[str, dict] = {}
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (len(seen) == 2 and statuses("".join(lines)) >= {"DCU-1", "DCU-2"}):
            time.sleep(1)
            try:
                nodes = get(f"{url}/api/nodes") if len(seen) < 2 else []
            except OSError:
                continue
            for node in nodes:
                stats = get(f"{url}/api/stats?node={node['node']}")
                if all((stats["stages"].get(stage) or {}).get("count", 0) > 0 for stage in FIVE):
                    seen[node["node"]] = stats
        assert set(seen) == {"DCU-1", "DCU-2"}, seen.keys()
        for stats in seen.values():
            assert stats["frame"]["count"] > 0 and stats["frame"]["mean_ms"] > 0
            # Native probes (the library the install built): every stage's delay splits into service and wait.
            infer = stats["stages"]["infer"]
            assert infer["service"]["count"] > 0 and infer["utilization"] is not None
            assert stats["bottleneck"]["reason"] and stats["bottleneck"]["utilization"] is not None
        page = urllib.request.urlopen(url + "/", timeout=10).read().decode()
        assert '<script src="vendor/socket.io.min.js">' in page
        vendored = urllib.request.urlopen(url + "/vendor/socket.io.min.js", timeout=10)
        assert vendored.status == 200 and len(vendored.read()) > 10_000
        demo.send_signal(signal.SIGINT)
        try:
            demo.wait(90)
        except subprocess.TimeoutExpired:
            raise AssertionError("the demo did not stop within 90 s of Ctrl-C:\n" + "".join(lines)) from None
        reader.join(10)
    finally:
        if demo.poll() is None:
            demo.kill()
    output = "".join(lines)
    assert demo.returncode == 128 + signal.SIGINT, output
    assert f"open {url}/" in output and "demo: stopped" in output and "Traceback" not in output
    assert statuses(output) >= {"DCU-1", "DCU-2"}, output


def test_without_gstreamer_headers_the_install_says_so_and_the_tool_says_what_to_install(installed, tmp_path):
    """Built where pkg-config finds no GStreamer (as without libgstreamer1.0-dev): the package builds,
    says why in one line, and the installed tool names the packages instead of compiling anything."""
    venv, env, _, _, _ = installed
    bare = dict(env, PKG_CONFIG_LIBDIR=str(tmp_path / "no-pc"))
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-v", "-w", str(tmp_path), str(REPO)],
                           env=bare, capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    said = [line.strip() for line in (built.stdout + built.stderr).splitlines() if "dcuscope: native probes not built" in line]
    assert said and "GStreamer development files not found" in said[0] and "libgstreamer1.0-dev" in said[0], said
    (wheel,) = tmp_path.glob("dcuscope-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "dcuscope/probes/capture/_build/libgstdcuscope.so" not in names
    assert "dcuscope/model/_build/libdcuscope_core.so" in names  # the compiled core needs no GStreamer
    state = zipfile.ZipFile(wheel).read("dcuscope/probes/capture/_build/BUILD-STATE").decode()
    assert state.startswith("GStreamer development files not found")

    again = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "--no-compile", "--no-deps", "--force-reinstall",
                            str(wheel)],
                           env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    found = dcuscope(installed, "plugin-path")
    assert found.returncode == 1 and len(found.stderr.splitlines()) == 1, found.stderr
    assert "installed without its native library (GStreamer development files not found" in found.stderr
    assert "install gcc pkg-config libgstreamer1.0-dev (Debian/Ubuntu names) and reinstall dcuscope" in found.stderr
    traced = dcuscope(installed, "trace", "-o", str(tmp_path / "app.jsonl"), "--", *GST_LAUNCH)
    assert traced.returncode != 0 and len(traced.stderr.splitlines()) == 1, traced.stderr
    assert "trace: no dcuscope GStreamer plugin: dcuscope was installed without its native library" in traced.stderr
    ran = dcuscope(installed, "run", "vtest", "--num-frames", "3", "--probes", "--trace", str(tmp_path / "t.jsonl"),
                   timeout=240)
    assert ran.returncode == 0, ran.stderr
    assert "probes: Python probes (no service/wait split), as the native library is unavailable: dcuscope was " \
           "installed without its native library" in ran.stderr
    assert not list((venv / "lib").rglob("libgstdcuscope.so"))  # nothing compiled into site-packages
