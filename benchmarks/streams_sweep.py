"""Streams sweep: the paper's Tables 4-6 (A = S/n per stream count) and Figure 12 (per-stage
delays vs stream count), measured on this machine, with each stage's delay split into service
and wait and the stage that limits throughput.

    .venv/bin/python benchmarks/streams_sweep.py                  # full sweep (long)
    .venv/bin/python benchmarks/streams_sweep.py --quick          # 3982 kbit/s, 30 fps, 1-2 streams, 8 s runs
    benchmarks/streams_sweep --model ssd --rates 30 --bitrates 4971 --max-streams 3 --all-streams \\
        --kinds file,rtsp,rtsp-late --duration 15 --warmup 5 --plot docs/streams_sweep.png   # BENCHMARKS.md's run

1. Clips. 1920x1080 H.264 clips (``--size``) at each frame rate and bitrate are made from the
   shipped clips (vtest.avi, bikes.mp4) with GStreamer (videoscale, videorate, x264enc, mp4mux)
   into a cache folder (default build/sweep-clips/); clips already there are kept.
2. Runs. For each input kind (``file``: local files played in real time by a synchronised
   sink; ``rtsp``: the same clips served live by ``dcuscope serve-rtsp`` on loopback;
   ``rtsp-late``: the same, with the mux's ``max-latency`` set to ``--late-ms``, so that it
   drops frames older than that instead of batching them), frame rate, bitrate and stream
   count 1..N, a config mux(batch-size=N, 1920x1080) -> infer -> tiler -> convert -> osd ->
   fakesink is written and run by ``dcuscope run --probes`` for ``--duration`` seconds (or, with
   ``--frames N``, until N collages reached the sink: as long as this machine needs), in its
   own process. The first ``--warmup`` seconds of frames are left out; the rest give, through
   ``probes.trace.delays.node_stats``: A = S/n (the mean frame delay of the frames that reached the
   sink), p95, fps per stream, every stage's mean delay, mean service and mean wait (delay =
   service + wait) and utilization, the bottleneck (the stage that limits throughput), and
   the frames each stream lost to ``max-latency``. A series stops at the first stream count
   whose fps per stream is under 90 % of the clip's rate (saturated) unless ``--all-streams``.
3. Output. Markdown tables (one per bitrate like the paper's Tables 4-6, and the per-stage
   data of Figure 12) on stdout and in ``--out``; the raw results as JSON next to it; a PNG
   plot (``--plot``, drawn by benchmarks/plot.py). A figure a run could not produce is
   ``n/a [k]`` in a table, its reason under "Notes" (benchmarks/figures.py); a clip that cannot
   be made stops the sweep with one line (exit status 2).

``--late-ms`` defaults to 200 ms: 6 frame periods at 30 fps. A live pipeline that keeps up
holds a frame far less than that between its decoder and the mux (BENCHMARKS.md: under 1 ms
mean, 10 ms at p99, with 200 ms of rtspsrc latency; under 100 ms at p99 with its default
2000 ms), while one that falls behind builds a backlog of seconds; 200 ms lets the first
through untouched and cuts the second.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, Notes, fmt, run  # noqa: E402
from dcuscope.probes.trace.delays import node_stats  # noqa: E402
from dcuscope.probes.trace.events import DROP_REASONS, FACT, LATE, ORIGIN  # noqa: E402
from dcuscope.probes.trace.tracefile import Trace, read_trace  # noqa: E402

MEDIA = ROOT / "assets" / "media"
MODELS = {"centernet": ROOT / "assets" / "models" / "centernet_mobilenetv3_coco80.onnx",
          "ssd": ROOT / "assets" / "models" / "ssdlite_mobilenetv2_person.onnx"}
CLIP_SOURCES = ("vtest.avi", "bikes.mp4")
"""Stream i plays a clip made from CLIP_SOURCES[i % 2]."""
KINDS = ("file", "rtsp", "rtsp-late")
"""Input kinds: local files; RTSP on loopback; RTSP with the mux dropping late frames."""
DEFAULT_LATE_MS = 200
"""The mux's max-latency of the ``rtsp-late`` kind (module docstring: why 200)."""
BITRATES = (3982, 4971, 7955)
"""kbit/s of the paper's clips; its Tables 4, 5 and 6."""
RATES = (30, 60)
STAGES = ("mux", "infer", "tiler", "convert", "osd")
WIDTH, HEIGHT = 1920, 1080
"""The paper's frame size: the clips', the mux's and the collage's (``--size`` another, e.g. for a smoke test)."""

DEFAULT_CACHE = ROOT / "build" / "sweep-clips"
DEFAULT_OUT = ROOT / "build" / "streams_sweep.md"
DEFAULT_CLIP_SECONDS = 10
DEFAULT_PRESET = "superfast"  # x264: quick to make on 2 cores; the bitrate is what the paper fixes
DEFAULT_DURATION = 20.0
DEFAULT_WARMUP = 5.0
DEFAULT_MAX_STREAMS = 4
SATURATION = 0.9
"""A stream count saturates the pipeline when its fps per stream is under this share of the clip's rate."""
START_ALLOWANCE_S = 60.0
"""Time a run may take beyond --duration (start-up, model load, end-of-stream drain) before it is killed."""
RTSP_READY_S = 30.0


# -- clips -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ClipSpec:
    source: str
    """File name in assets/media."""
    fps: int
    bitrate: int
    """kbit/s."""
    seconds: int
    preset: str = DEFAULT_PRESET
    width: int = WIDTH
    height: int = HEIGHT

    @property
    def name(self) -> str:
        stem = Path(self.source).stem
        size = f"{self.height}p" if self.width * 9 == self.height * 16 else f"{self.width}x{self.height}"
        return f"{stem}_{size}{self.fps}_{self.bitrate}k_{self.seconds}s_{self.preset}.mp4"


def clip_pipeline(spec: ClipSpec, target: Path) -> str:
    """gst-launch description that turns a shipped clip into ``spec`` at ``target``."""
    caps = (f"video/x-raw,format=I420,width={spec.width},height={spec.height},pixel-aspect-ratio=1/1,"
            f"framerate={spec.fps}/1")
    # Letterboxed (add-borders) rather than stretched, so that people keep their shape for the detector.
    return (f'filesrc location="{MEDIA / spec.source}" ! decodebin ! videoconvert name=first ! videoscale add-borders=true '
            f"! videorate name=rate ! {caps} ! x264enc bitrate={spec.bitrate} speed-preset={spec.preset} "
            f"key-int-max={spec.fps} ! h264parse ! mp4mux ! filesink location=\"{target}\"")


def make_clip(spec: ClipSpec, cache: Path, progress: Callable[[str], None] = lambda _: None,
              timeout_s: float = 600.0) -> Path:
    """Encode ``spec`` into ``cache`` unless it is there already; return its path."""
    from dcuscope.core.gst import Gst

    target = cache / spec.name
    if target.is_file() and target.stat().st_size > 0:
        return target
    cache.mkdir(parents=True, exist_ok=True)
    part = target.with_suffix(".part.mp4")  # renamed when complete: a killed run leaves no half clip
    pipeline = Gst.parse_launch(clip_pipeline(spec, part))
    limit = spec.seconds * Gst.SECOND
    ended = []

    def cut(pad, info):
        # Ends the clip at its length: a seek cannot go through the encoder and muxer, and
        # mp4mux only finalises the file on EOS. Frames after the end are dropped.
        if info.get_buffer().pts < limit:
            return Gst.PadProbeReturn.OK
        if not ended:
            ended.append(True)
            pad.push_event(Gst.Event.new_eos())
        return Gst.PadProbeReturn.DROP

    def skip(_pad, info):
        # Spares scaling the rest of a long source to the clip's size (videorate may still need a frame past the end).
        late = info.get_buffer().pts >= limit + Gst.SECOND
        return Gst.PadProbeReturn.DROP if late else Gst.PadProbeReturn.OK

    # The cut is after videorate: at EOS it repeats the last frame to fill out the source's own duration.
    pipeline.get_by_name("rate").get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, cut)
    pipeline.get_by_name("first").get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, skip)
    try:
        pipeline.set_state(Gst.State.PLAYING)
        bus = pipeline.get_bus()
        deadline = time.monotonic() + timeout_s
        while True:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{spec.name}: not made within {timeout_s:.0f} s")
            msg = bus.timed_pop_filtered(2 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
            if msg is None:
                ok, pos = pipeline.query_position(Gst.Format.TIME)
                if ok:
                    progress(f"  {spec.name}: {min(100, 100 * pos / limit):3.0f} %")
                continue
            if msg.type == Gst.MessageType.ERROR:
                err, debug = msg.parse_error()
                raise RuntimeError(f"{spec.name}: {err.message} ({debug})")
            break
    finally:
        pipeline.set_state(Gst.State.NULL)
    part.rename(target)
    return target


def clip_for(stream: int, fps: int, bitrate: int, seconds: int, preset: str,
             size: tuple[int, int] = (WIDTH, HEIGHT)) -> ClipSpec:
    return ClipSpec(CLIP_SOURCES[stream % len(CLIP_SOURCES)], fps, bitrate, seconds, preset, *size)


# -- configurations ----------------------------------------------------------------------------
def grid(streams: int) -> tuple[int, int]:
    """(rows, columns) of the collage: as square as possible, wider than tall."""
    columns = math.ceil(math.sqrt(streams))
    return math.ceil(streams / columns), columns


def config_text(kind: str, uris: list[str], fps: int, model: str, late_ms: int = DEFAULT_LATE_MS,
                size: tuple[int, int] = (WIDTH, HEIGHT)) -> str:
    """A dcuscope YAML config for one run: the paper's chain over ``uris`` at 1080p (``size``);
    ``late_ms`` is the mux's max-latency of the ``rtsp-late`` kind."""
    n = len(uris)
    rows, columns = grid(n)
    width, height = size
    if kind == "file":
        sources = "\n".join(f"  - {{uri: '{u}', loop: true}}" for u in uris)
        mux = f"{{batch-size: {n}, width: {width}, height: {height}}}"
        # sync: the file plays at its own rate, as the paper's file input did (else as fast as possible).
        sink = "{type: fake, sync: true}"
    else:
        sources = "\n".join(f"  - {{uri: '{u}'}}" for u in uris)
        # nvstreammux's advice: batched-push-timeout = one frame period of the fastest source.
        late = f", max-latency: {late_ms}" if kind == "rtsp-late" else ""
        mux = (f"{{batch-size: {n}, width: {width}, height: {height}, live-source: true, "
               f"batched-push-timeout: {1_000_000 // fps}{late}}}")
        # Live sources pace themselves; a synchronised sink would only add the jitter buffer's
        # latency as a wait after the last tracepoint, as in configs/rtsp.yaml.
        sink = "{type: fake}"
    return f"""\
node: sweep
sources:
{sources}
stages:
  - mux: {mux}
  - infer: {{model: '{MODELS[model]}', threshold: 0.3}}
  - tiler: {{rows: {rows}, columns: {columns}, width: {width}, height: {height}}}
  - convert: {{format: RGBA}}
  - osd: {{line-width: 3}}
sink: {sink}
"""


# -- processes ---------------------------------------------------------------------------------
def cli_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("GST_DEBUG", "0")
    return env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RtspServer:
    """``dcuscope serve-rtsp`` in its own process for the duration of a ``with`` block."""

    def __init__(self, clips: list[Path], bitrate: int):
        self.clips, self.bitrate = clips, bitrate
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        self._errors = tempfile.TemporaryFile()  # not a pipe: nobody reads it while it serves
        self._started = 0.0
        self.cores: float | None = None
        """CPU cores the server used while it ran (measured when it stops)."""

    @property
    def uris(self) -> list[str]:
        return [f"rtsp://127.0.0.1:{self.port}/cam{i}" for i in range(len(self.clips))]

    def __enter__(self) -> "RtspServer":
        # Unbuffered stdout: select() then sees every announced line (a buffered reader would
        # swallow several lines at once and leave select() waiting for nothing).
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dcuscope.cli", "serve-rtsp", *map(str, self.clips), "--port", str(self.port),
             "--bitrate", str(self.bitrate)],
            cwd=ROOT, env=cli_env(), stdout=subprocess.PIPE, stderr=self._errors, bufsize=0)
        self._started = time.monotonic()
        deadline = time.monotonic() + RTSP_READY_S
        announced = b""
        try:
            # It announces one line per mount once it listens.
            while announced.count(b"rtsp://") < len(self.clips):
                ready, _, _ = select.select([self.proc.stdout], [], [], max(deadline - time.monotonic(), 0))
                chunk = os.read(self.proc.stdout.fileno(), 4096) if ready else b""
                if not chunk:
                    self._errors.seek(0)
                    raise RuntimeError(f"serve-rtsp did not start within {RTSP_READY_S:.0f} s: "
                                       f"{self._errors.read()[-500:].decode(errors='replace')}")
                announced += chunk
        except BaseException:
            self.__exit__()
            raise
        return self

    def _cpu_cores(self) -> float | None:
        try:  # utime + stime, fields 14 and 15 of /proc/PID/stat (after the command name)
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            cpu_s = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError):
            return None
        return cpu_s / max(time.monotonic() - self._started, 1e-3)

    def __exit__(self, *_exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.cores = self._cpu_cores()
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if self.proc is not None:
            self.proc.stdout.close()
        self._errors.close()


def run_pipeline(config: Path, trace: Path, duration: float, frames: int | None = None) -> tuple[int, str]:
    """``dcuscope run CONFIG --probes`` for ``duration`` s, or until ``frames`` collages reached the
    sink (``duration``: how long they take at the clips' rate; a busy machine may take four times
    that), killed if it overruns; (exit status, stderr tail)."""
    stop = ["--num-frames", str(frames)] if frames else ["--duration", str(duration)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes", "--trace", str(trace), *stop, "-q"],
        cwd=ROOT, env=cli_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, stderr = proc.communicate(timeout=(4 if frames else 1) * duration + START_ALLOWANCE_S)
    except subprocess.TimeoutExpired:
        proc.kill()  # the trace reader accepts the cut file
        _, stderr = proc.communicate()
        return -9, (stderr or "")[-500:] + "\n(killed: overran its time)"
    finally:
        if proc.poll() is None:  # interrupted: leave no pipeline behind
            proc.kill()
            proc.wait()
    return proc.returncode, (stderr or "")[-500:]


# -- measurement (pure) ------------------------------------------------------------------------
def after_warmup(events: np.ndarray, warmup_s: float) -> np.ndarray:
    """The events of the frames that originated ``warmup_s`` or more after the first origin, and
    every fact (which thread pushes each stage: the bottleneck needs it; facts are sent when
    they change, mostly at the start)."""
    origins = events[events["point"] == ORIGIN]
    if len(origins) == 0 or warmup_s <= 0:
        return events
    cutoff = int(origins["ts"].min()) + int(warmup_s * 1e9)
    late = origins[origins["ts"] >= cutoff]
    keys = (events["source"].astype(np.int64) << 40) | events["frame"].astype(np.int64)
    keep = (late["source"].astype(np.int64) << 40) | late["frame"].astype(np.int64)
    return events[np.isin(keys, keep) | (events["point"] == FACT)]


@dataclass
class Measurement:
    a_ms: float | None
    """The paper's A = S/n: mean frame delay (origin -> sink) of the complete frames."""
    p95_ms: float | None
    fps: float
    """Mean over the streams of each stream's complete frames per second."""
    stages_ms: dict[str, float]
    """Mean delay of each of STAGES (exit - enter)."""
    queues_ms: float
    """A minus the sum of the stage means: waits between stages (hand-over, back-pressure)."""
    frames: int
    incomplete: int
    service_ms: dict[str, float] = field(default_factory=dict)
    """Mean service of each of STAGES that has one: its own work on the buffer that carried the frame out."""
    wait_ms: dict[str, float] = field(default_factory=dict)
    """Mean wait of the same stages (queued, waiting for a batch, blocked downstream): delay = service + wait."""
    utilization: dict[str, float] = field(default_factory=dict)
    """Busy fraction of the run's span of each stage with service times."""
    bottleneck: dict | None = None
    """``{stage, utilization, thread_utilization, saturated}`` of probes.trace.delays.bottleneck."""
    delivered: dict[str, int] = field(default_factory=dict)
    """Source id -> frames that reached their origin (decoded and stamped)."""
    late: dict[str, int] = field(default_factory=dict)
    """Source id -> of those, frames the mux dropped as older than its max-latency."""


BOTTLENECK_KEYS = ("stage", "utilization", "thread_utilization", "saturated")


def measure(trace: Trace, warmup_s: float) -> Measurement:
    stats = node_stats(trace.header, after_warmup(trace.events, warmup_s), trace.dropped)
    frame, per_stage = stats["frame"], {s: stats["stages"][s] for s in STAGES if s in stats["stages"]}
    stages = {s: st["mean_ms"] for s, st in per_stage.items()}
    fps = list(stats["fps"].values())
    a_ms = frame["mean_ms"]
    queues = a_ms - sum(v for v in stages.values() if v is not None) if a_ms is not None else 0.0
    timed = {s: st for s, st in per_stage.items() if st["service"]["count"]}
    neck = stats["bottleneck"]
    return Measurement(
        a_ms=a_ms, p95_ms=frame["p95_ms"], fps=float(np.mean(fps)) if fps else 0.0, stages_ms=stages,
        queues_ms=queues, frames=stats["frames"]["complete"], incomplete=stats["frames"]["incomplete"],
        service_ms={s: st["service"]["mean_ms"] for s, st in timed.items()},
        wait_ms={s: st["wait"]["mean_ms"] for s, st in timed.items()},
        utilization={s: st["utilization"] for s, st in timed.items() if st["utilization"] is not None},
        bottleneck={k: neck[k] for k in BOTTLENECK_KEYS} if neck else None,
        delivered={sid: src["delivered"] for sid, src in stats["sources"].items()},
        late={sid: src["dropped"].get(DROP_REASONS[LATE], 0) for sid, src in stats["sources"].items()})


def saturated(fps: float, rate: float) -> bool:
    return fps < SATURATION * rate


# -- the sweep ---------------------------------------------------------------------------------
@dataclass
class Point:
    kind: str
    fps: int
    bitrate: int
    streams: int


@dataclass
class Result:
    kind: str
    fps: int
    bitrate: int
    streams: int
    a_ms: float | None = None
    p95_ms: float | None = None
    achieved_fps: float = 0.0
    stages_ms: dict[str, float] = field(default_factory=dict)
    queues_ms: float = 0.0
    frames: int = 0
    incomplete: int = 0
    saturated: bool = False
    error: str = ""
    wall_s: float = 0.0
    load: float = 0.0
    """1-minute load average at the end of the run: this machine is shared."""
    server_cores: float | None = None
    """RTSP: CPU cores that serve-rtsp (decoding and re-encoding on this machine) used."""
    runs: int = 1
    """Repetitions the figures are the median of."""
    service_ms: dict[str, float] = field(default_factory=dict)
    wait_ms: dict[str, float] = field(default_factory=dict)
    utilization: dict[str, float] = field(default_factory=dict)
    bottleneck: dict | None = None
    delivered: dict[str, int] = field(default_factory=dict)
    late: dict[str, int] = field(default_factory=dict)
    """These six as :class:`Measurement`'s."""
    max_latency_ms: int = 0
    """The mux's max-latency of the run (0: off)."""

    def take(self, m: Measurement) -> None:
        """Copy the figures of ``m``."""
        self.a_ms, self.p95_ms, self.achieved_fps, self.stages_ms = m.a_ms, m.p95_ms, m.fps, m.stages_ms
        self.queues_ms, self.frames, self.incomplete = m.queues_ms, m.frames, m.incomplete
        self.service_ms, self.wait_ms, self.utilization = m.service_ms, m.wait_ms, m.utilization
        self.bottleneck = m.bottleneck
        self.delivered, self.late = m.delivered, m.late
        self.saturated = saturated(m.fps, self.fps)


def _median(values) -> float | None:
    """The median of the values that are not None; None when every one is (kept as None in the
    results' JSON, which benchmarks/plot.py reads; the tables say why)."""
    present = [v for v in values if v is not None]
    return float(np.median(present)) if present else None


def _medians(dicts: list[dict]) -> dict:
    """Key -> the median of its values over the dicts that have it (keys in first-seen order)."""
    keys = dict.fromkeys(k for d in dicts for k in d)
    return {k: _median([d[k] for d in dicts if k in d]) for k in keys}


def combine_bottleneck(necks: list[dict | None]) -> dict | None:
    """The stage named most often (the earliest on a tie), with the medians of its figures over
    the runs that named it; saturated when most of those runs said so."""
    named = [b for b in necks if b]
    if not named:
        return None
    stages = [b["stage"] for b in named]
    stage = max(dict.fromkeys(stages), key=stages.count)
    same = [b for b in named if b["stage"] == stage]

    def figure(key: str) -> float | None:
        return _median([b[key] for b in same]) if all(b[key] is not None for b in same) else None

    return {"stage": stage, "utilization": figure("utilization"), "thread_utilization": figure("thread_utilization"),
            "saturated": 2 * sum(bool(b["saturated"]) for b in same) > len(same)}


def combine(results: list[Result]) -> Result:
    """One result from repetitions of one point: the median of each figure over the runs that measured."""
    ok = [r for r in results if r.a_ms is not None]
    if not ok:
        return results[0]
    first = ok[0]
    cores = [r.server_cores for r in ok if r.server_cores is not None]
    return Result(
        first.kind, first.fps, first.bitrate, first.streams, a_ms=_median([r.a_ms for r in ok]),
        p95_ms=_median([r.p95_ms for r in ok]), achieved_fps=_median([r.achieved_fps for r in ok]),
        stages_ms=_medians([r.stages_ms for r in ok]), queues_ms=_median([r.queues_ms for r in ok]),
        frames=sum(r.frames for r in ok), incomplete=sum(r.incomplete for r in ok),
        saturated=saturated(_median([r.achieved_fps for r in ok]), first.fps),
        error="; ".join(dict.fromkeys(r.error for r in results if r.error)), wall_s=sum(r.wall_s for r in results),
        load=_median([r.load for r in ok]), server_cores=_median(cores), runs=len(ok),
        service_ms=_medians([r.service_ms for r in ok]), wait_ms=_medians([r.wait_ms for r in ok]),
        utilization=_medians([r.utilization for r in ok]), bottleneck=combine_bottleneck([r.bottleneck for r in ok]),
        delivered=_medians([r.delivered for r in ok]), late=_medians([r.late for r in ok]),
        max_latency_ms=first.max_latency_ms)


def series(kinds, rates, bitrates, bitrates_at: dict[int, list[int]] | None = None) -> Iterator[tuple[str, int, int]]:
    """(kind, fps, bitrate) of every series, bitrate-major; ``bitrates_at`` narrows the bitrates of a rate."""
    for bitrate in bitrates:
        for kind in kinds:
            for fps in rates:
                if bitrate in (bitrates_at or {}).get(fps, [bitrate]):
                    yield kind, fps, bitrate


def run_point(point: Point, clips: list[Path], model: str, duration: float, warmup: float, workdir: Path,
              rep: int = 1, late_ms: int = DEFAULT_LATE_MS, size: tuple[int, int] = (WIDTH, HEIGHT),
              frames: int | None = None) -> Result:
    """One run of ``point`` for ``duration`` s, or until ``frames`` collages reached the sink."""
    if frames:
        duration = frames / point.fps
    result = Result(point.kind, point.fps, point.bitrate, point.streams,
                    max_latency_ms=late_ms if point.kind == "rtsp-late" else 0)
    started = time.monotonic()
    tag = f"{point.kind}-{point.fps}-{point.bitrate}-{point.streams}-{rep}"
    config, trace = workdir / f"{tag}.yaml", workdir / f"{tag}.jsonl"
    try:
        if point.kind == "file":
            config.write_text(config_text("file", [c.as_uri() for c in clips], point.fps, model, size=size))
            status, stderr = run_pipeline(config, trace, duration, frames)
        else:
            with RtspServer(clips, point.bitrate) as server:
                config.write_text(config_text(point.kind, server.uris, point.fps, model, late_ms, size))
                status, stderr = run_pipeline(config, trace, duration, frames)
            result.server_cores = server.cores
        if not trace.is_file():
            raise RuntimeError(f"no trace (exit status {status}): {stderr.strip()}")
        m = measure(read_trace(trace), warmup)
        result.take(m)
        if status != 0:
            result.error = f"exit status {status}: {stderr.strip().splitlines()[-1] if stderr.strip() else ''}"
        if m.a_ms is None:
            result.error = result.error or "no complete frame after the warm-up"
            result.saturated = True
    except (RuntimeError, OSError) as exc:
        result.error = str(exc)
        result.saturated = True
    result.wall_s = time.monotonic() - started
    result.load = os.getloadavg()[0]
    return result


def machine() -> str:
    """CPU count and model, memory and load: the figures only mean something next to these."""
    model = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
        mem_kb = int(Path("/proc/meminfo").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        mem_kb = 0
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{os.cpu_count()} CPUs ({model}), {mem_kb / 2**20:.0f} GiB RAM, {platform.system()} "
            f"{platform.release()}, load average {load}")


def run_length(args: argparse.Namespace) -> str:
    """How long each run is: "20 s", or "40 frames" (--frames)."""
    return f"{args.frames} frames" if args.frames else f"{args.duration:g} s"


def fmt_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


def sweep(args: argparse.Namespace, log: Callable[[str], None],
          on_result: Callable[[list[Result]], None] = lambda _: None) -> list[Result]:
    """Make the clips, then run every point of the plan; ``on_result`` sees the results so far after each run."""
    from dcuscope.core.gst import GLib

    plan = list(series(args.kinds, args.rates, args.bitrates, args.bitrates_at))
    specs = sorted({clip_for(i, fps, b, args.clip_seconds, args.preset, args.size)
                    for _, fps, b in plan for i in range(min(args.max_streams, len(CLIP_SOURCES)))},
                   key=lambda s: (s.fps, s.bitrate, s.source))
    missing = [s for s in specs if not (args.cache / s.name).is_file()]
    log(f"clips: {len(specs)} needed, {len(missing)} to make in {args.cache}")
    for i, spec in enumerate(missing, 1):
        t0 = time.monotonic()
        log(f"[clip {i}/{len(missing)}] {spec.name}")
        try:
            make_clip(spec, args.cache, progress=log)
        except (RuntimeError, OSError, GLib.Error) as exc:  # GLib.Error: an element of its pipeline is missing
            raise CannotRun(f"cannot make the clip {spec.name}: {getattr(exc, 'message', exc)}") from exc
        log(f"  made in {time.monotonic() - t0:.1f} s")

    runs: dict[tuple, list[Result]] = {}  # point -> its repetitions, in the order first run

    def report() -> list[Result]:
        combined = [combine(rs) for rs in runs.values()]
        on_result(combined)
        return combined

    runs_left = len(plan) * args.max_streams * args.repeat  # an upper bound: a saturated series stops early
    per_run = (args.frames / min(args.rates) if args.frames else args.duration) + 10.0  # first guess; then the mean
    done = 0
    spent = 0.0

    def run(point: Point, rep: int, workdir: Path) -> Result:
        nonlocal runs_left, per_run, done, spent
        clips = [args.cache / clip_for(i, point.fps, point.bitrate, args.clip_seconds, args.preset, args.size).name
                 for i in range(point.streams)]
        log(f"[run {done + 1}, at most {runs_left} left, eta <= {fmt_duration(runs_left * per_run)}] "
            f"{point.kind} {point.fps} fps {point.bitrate} kbit/s, {point.streams} stream(s), {run_length(args)}"
            + (f", repetition {rep}/{args.repeat}" if args.repeat > 1 else ""))
        r = run_point(point, clips, args.model, args.duration, args.warmup, workdir, rep, args.late_ms, args.size,
                      args.frames)
        runs.setdefault((point.kind, point.fps, point.bitrate, point.streams), []).append(r)
        done, runs_left, spent = done + 1, runs_left - 1, spent + r.wall_s
        per_run = spent / done
        log("    " + describe(r))
        report()
        return r

    with tempfile.TemporaryDirectory(prefix="streams-sweep-") as tmp:
        workdir = args.keep_traces or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        measured: list[Point] = []
        for kind, fps, bitrate in plan:
            for streams in range(1, args.max_streams + 1):
                point = Point(kind, fps, bitrate, streams)
                measured.append(point)
                r = run(point, 1, workdir)
                if r.saturated and not args.all_streams:
                    runs_left -= (args.max_streams - streams) * args.repeat
                    break
        # Repetitions go round the whole plan again, so that the load of this shared machine at
        # one moment does not weigh on one point only.
        runs_left = len(measured) * (args.repeat - 1)
        for rep in range(2, args.repeat + 1):
            for point in measured:
                run(point, rep, workdir)
    return report()


def describe(r: Result) -> str:
    if r.a_ms is None:
        return f"failed: {_failure(r)}"
    stages = " ".join(f"{s} {_split(r, s)}" for s in r.stages_ms)
    text = (f"A {r.a_ms:.1f} ms, p95 {fmt(r.p95_ms, '.1f', ' ms', NO_P95)}, {r.achieved_fps:.1f} fps/stream"
            f"{' SATURATED' if r.saturated else ''} | limit {_limit(r.bottleneck)} | service/wait {stages} "
            f"between {r.queues_ms:.1f} ms | late drops {_late(r)} | {r.frames} frames, {r.wall_s:.0f} s, "
            f"load {r.load:.1f}"
            + (f", serve-rtsp {r.server_cores:.2f} cores" if r.server_cores is not None else ""))
    return text + (f" | {r.error}" if r.error else "")


# -- report (pure) -----------------------------------------------------------------------------
NO_P95 = "no p95 of the frame delay"


class _Inline:
    """Notes that put the reason in the cell: ``n/a (reason)`` (the run log's lines)."""

    def cell(self, x, spec: str = "", unit: str = "", why: str = "not measured") -> str:
        return fmt(x, spec, unit, why)


def _failure(r: Result) -> str:
    """Why a run gave no A."""
    return r.error or "no complete frame after the warm-up"


def _cell(r: Result | None, notes: Notes | None = None) -> str:
    """A as "40.0 (p95 60) @ 30.0"; – for a point not run; n/a with the reason of a failed run
    (``n/a [k]`` when ``notes`` take the reasons)."""
    notes = _Inline() if notes is None else notes
    if r is None:
        return "–"
    if r.a_ms is None:
        return notes.cell(NA(_failure(r)))
    p95 = notes.cell(r.p95_ms, ".0f", why=NO_P95)
    return f"{r.a_ms:.1f} (p95 {p95}) @ {r.achieved_fps:.1f}{'*' if r.saturated else ''}"


def _split(r: Result, stage: str, notes: Notes | None = None) -> str:
    """"service/wait" in ms, or the delay alone when the stage has no service times."""
    notes = _Inline() if notes is None else notes
    if stage in r.service_ms:
        return f"{r.service_ms[stage]:.1f}/{r.wait_ms[stage]:.1f}"
    return notes.cell(r.stages_ms.get(stage), ".1f", why=f"no frame passed {stage} after the warm-up")


def _limit(neck: dict | None, notes: Notes | None = None) -> str:
    """The bottleneck as "infer 97 % sat." or "infer 62 % (thread 97 %) sat."."""
    notes = _Inline() if notes is None else notes
    if not neck:
        return notes.cell(NA("no stage had a delay after the warm-up: no bottleneck"))
    if neck["utilization"] is None:
        return f"{neck['stage']} " + notes.cell(NA("no service times in the trace: the utilization is unknown"))
    thread = neck["thread_utilization"]
    shared = f" (thread {thread:.0%})" if thread is not None and thread >= neck["utilization"] + 0.005 else ""
    return f"{neck['stage']} {neck['utilization']:.0%}{shared}{' sat.' if neck['saturated'] else ''}"


def _late(r: Result) -> str:
    """Frames dropped late per stream, and their share of the frames delivered; – without max-latency."""
    if not r.max_latency_ms and not any(r.late.values()):
        return "–"
    per_stream = ", ".join(f"{n:.0f}" for n in r.late.values()) or "0"
    delivered = sum(r.delivered.values())
    return per_stream + (f" ({sum(r.late.values()) / delivered:.0%})" if delivered else "")


def _a_tables(results: list[Result], model: str, notes: Notes) -> list[str]:
    """Tables 4-6: A = S/n per stream count, one table per bitrate, a column per kind and rate."""
    out = []
    columns = [(k, f) for k in KINDS for f in RATES if any(r.kind == k and r.fps == f for r in results)]
    paper_table = {b: f"Table {4 + i}" for i, b in enumerate(BITRATES)}
    for bitrate in sorted({r.bitrate for r in results}):
        rows = sorted({r.streams for r in results if r.bitrate == bitrate})
        title = f"{bitrate} kbit/s" + (f" (paper's {paper_table[bitrate]})" if bitrate in paper_table else "")
        out += [f"#### A = S/n per stream count, {title}, model {model}", "",
                "| streams | " + " | ".join(f"{k} {f} fps" for k, f in columns) + " |",
                "|---:|" + "---:|" * len(columns)]
        for n in rows:
            cells = [_cell(next((r for r in results if (r.kind, r.fps, r.bitrate, r.streams) == (k, f, bitrate, n)),
                                None), notes) for k, f in columns]
            out.append(f"| {n} | " + " | ".join(cells) + " |")
        out.append("")
    return out + ["Cells: A in ms (p95 in ms) @ achieved frames/s per stream; * saturated (under "
                  f"{SATURATION:.0%} of the clip's rate); – not run; a figure a run could not produce refers to "
                  "its reason under Notes.", ""]


def _stage_table(results: list[Result], model: str, notes: Notes) -> list[str]:
    """Figure 12's data: per run the limiting stage, service/wait of every stage, late drops."""
    out = [f"#### Per-stage mean service/wait (ms), Figure 12's data, model {model}", "",
           "| input | fps | kbit/s | streams | limiting stage | " + " | ".join(STAGES)
           + " | between | A | p95 | fps/stream | late drops | load | serve-rtsp cores |",
           "|---|---:|---:|---:|---|" + "---:|" * (len(STAGES) + 7)]
    def order(r: Result) -> tuple:
        return KINDS.index(r.kind) if r.kind in KINDS else len(KINDS), r.fps, r.bitrate, r.streams

    for r in sorted(results, key=order):
        if r.a_ms is None:
            continue
        stages = " | ".join(_split(r, s, notes) for s in STAGES)
        out.append(f"| {r.kind} | {r.fps} | {r.bitrate} | {r.streams} | {_limit(r.bottleneck, notes)} | {stages} | "
                   f"{r.queues_ms:.1f} | {r.a_ms:.1f} | {notes.cell(r.p95_ms, '.1f', why=NO_P95)} | "
                   f"{r.achieved_fps:.1f}{'*' if r.saturated else ''} | {_late(r)} | {r.load:.1f} | "
                   f"{'–' if r.server_cores is None else f'{r.server_cores:.2f}'} |")
    runs = sorted({r.runs for r in results})
    late_ms = sorted({r.max_latency_ms for r in results if r.max_latency_ms})
    return out + ["", "Stage cells: mean service/wait in ms (delay = service + wait; service is the stage's own "
                  "work on the buffer that carried the frame out, wait is queued, waiting for a batch or blocked "
                  "downstream). limiting stage: probes.trace.delays' bottleneck with its utilization (busy fraction of "
                  "the run), its streaming thread's when other stages share it, sat. when that thread is saturated "
                  "(>= 90 %). between = A minus the sum of the stage delays: gaps between stages. late drops: "
                  "frames per stream the mux dropped as older than its max-latency"
                  + (f" ({'/'.join(map(str, late_ms))} ms)" if late_ms else "")
                  + ", and their share of the frames decoded. load: 1-minute load average after the run. "
                  "serve-rtsp cores: CPU the RTSP server (decoding and re-encoding every stream on this same "
                  "machine) used."
                  + (f" Figures are medians of {'/'.join(map(str, runs))} runs per point." if runs != [1] else "")]


def markdown(results: list[Result], model: str, preamble: list[str] = ()) -> str:
    """Tables 4-6 (one per bitrate) and the per-stage data of Figure 12, after ``preamble`` lines."""
    out = [*preamble, ""] if preamble else []
    notes = Notes()
    out += _a_tables(results, model, notes) + _stage_table(results, model, notes)
    failed = [r for r in results if r.error]
    if failed or notes:
        out += ["", "Notes:"] + [f"- {line}" for line in notes.lines()] + [
            f"- {r.kind} {r.fps} fps {r.bitrate} kbit/s {r.streams} stream(s): {r.error}" for r in failed]
    return "\n".join(out) + "\n"


# -- command line ------------------------------------------------------------------------------
def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def _size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    size = int(width), int(height)
    if min(size) < 16 or any(x % 2 for x in size):
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT, each even and at least 16")
    return size


def _rate_bitrates(text: str) -> tuple[int, list[int]]:
    fps, _, kbps = text.partition("=")
    return int(fps), [int(k) for k in kbps.split("+") if k]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="short run: one bitrate (3982), 30 fps only, at most 2 streams, 8 s runs, 3 s warm-up")
    p.add_argument("--model", choices=sorted(MODELS), default="centernet",
                   help="detector: centernet (80 classes, the product's default) or ssd (persons, much faster)")
    p.add_argument("--kinds", type=lambda t: t.split(","), default=list(KINDS[:2]),
                   help="input kinds, of file, rtsp and rtsp-late (RTSP with the mux's max-latency at --late-ms); "
                        "default file,rtsp")
    p.add_argument("--late-ms", type=int, default=DEFAULT_LATE_MS,
                   help=f"max-latency of the mux for rtsp-late, ms (default {DEFAULT_LATE_MS}: 6 frame periods at 30 fps)")
    p.add_argument("--rates", type=_ints, default=list(RATES), help="clip frame rates (default 30,60)")
    p.add_argument("--bitrates", type=_ints, default=list(BITRATES), help="clip bitrates, kbit/s (default 3982,4971,7955)")
    p.add_argument("--bitrates-at", type=_rate_bitrates, action="append", default=[], metavar="FPS=KBPS[+KBPS]",
                   help="only these bitrates at this frame rate, e.g. 60=3982 (repeatable)")
    p.add_argument("--max-streams", type=int, default=DEFAULT_MAX_STREAMS, help="highest stream count (default 4)")
    p.add_argument("--all-streams", action="store_true", help="go on to --max-streams past saturation")
    p.add_argument("--repeat", type=int, default=1,
                   help="run every point this many times, a pass over the plan at a time; report medians")
    p.add_argument("--duration", type=float, default=DEFAULT_DURATION, help="seconds per run (default 20)")
    p.add_argument("--frames", type=int, metavar="N",
                   help="instead of --duration: each run stops once N collages reached the sink, as long as this "
                        "machine takes (the frames after the warm-up do not depend on its load)")
    p.add_argument("--warmup", type=float, default=DEFAULT_WARMUP, help="seconds of frames left out at the start (default 5)")
    p.add_argument("--clip-seconds", type=int, default=DEFAULT_CLIP_SECONDS, help="length of the clips made (default 10)")
    p.add_argument("--size", type=_size, default=(WIDTH, HEIGHT), metavar="WxH",
                   help=f"frame size of the clips, the mux and the collage (default {WIDTH}x{HEIGHT}, the paper's)")
    p.add_argument("--preset", default=DEFAULT_PRESET, help=f"x264 speed-preset of the clips (default {DEFAULT_PRESET})")
    p.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="clip folder (default build/sweep-clips)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Markdown results (default build/streams_sweep.md); "
                   "the raw results go to the same name with .json")
    p.add_argument("--plot", type=Path, help="PNG plot (default: --out with .png)")
    p.add_argument("--keep-traces", type=Path, metavar="DIR", help="keep the configs and traces of the runs here")
    args = p.parse_args(argv)
    if args.quick:
        args.bitrates, args.rates = args.bitrates[:1], [30]
        args.max_streams, args.duration, args.warmup = min(args.max_streams, 2), 8.0, 3.0
    bad = [k for k in args.kinds if k not in KINDS]
    # the run's length in seconds of the clips: the warm-up must leave some of it
    length = args.frames / max(args.rates) if args.frames else args.duration
    if bad or args.max_streams < 1 or args.repeat < 1 or args.warmup >= length or args.late_ms < 1 or (
            args.frames is not None and args.frames < 1):
        p.error(f"unknown kinds {bad} (known: {', '.join(KINDS)})" if bad else
                "need --max-streams >= 1, --repeat >= 1, --late-ms >= 1, --frames >= 1 and --warmup < --duration "
                "(with --frames: < N / the highest --rates)")
    args.plot = args.plot or args.out.with_suffix(".png")
    args.bitrates_at = dict(args.bitrates_at)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()

    def log(line: str) -> None:
        print(f"[{fmt_duration(time.monotonic() - started):>6}] {line}", file=sys.stderr, flush=True)

    command = " ".join(["benchmarks/streams_sweep.py", *(sys.argv[1:] if argv is None else argv)])
    preamble = [f"- command: `{command}`", f"- date: {time.strftime('%Y-%m-%d %H:%M %Z')}",
                f"- machine at the start: {machine()}",
                f"- runs: {run_length(args)} each, first {args.warmup:g} s of frames left out; clips "
                f"{args.size[0]}x{args.size[1]}, {args.clip_seconds} s, x264 {args.preset}, looped; model {args.model}"
                + (f"; rtsp-late: the mux's max-latency {args.late_ms} ms" if "rtsp-late" in args.kinds else "")]
    args.out.parent.mkdir(parents=True, exist_ok=True)

    def save(results: list[Result], final: bool = False) -> str:
        # Written after every run, so that an interrupted sweep keeps what it measured.
        lines = preamble + [f"- machine at the end: {machine()}"] if final else preamble
        text = markdown(results, args.model, lines)
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(
            {"model": args.model, "duration_s": None if args.frames else args.duration, "frames": args.frames,
             "warmup_s": args.warmup, "late_ms": args.late_ms,
             "size": list(args.size),
             "command": command,
             "results": [asdict(r) for r in results]}, indent=1))
        return text

    results = sweep(args, log, save)
    print(save(results, final=True))
    from benchmarks.plot import draw_sweep

    draw_sweep([asdict(r) for r in results], args.plot, title=f"dcuscope streams sweep, model {args.model}")
    log(f"done in {fmt_duration(time.monotonic() - started)}: {args.out}, {args.out.with_suffix('.json')}, {args.plot}")
    return 0 if all(r.a_ms is not None for r in results) else 1


if __name__ == "__main__":
    sys.exit(run(main))
