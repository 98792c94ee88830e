"""Streams sweep: the paper's Tables 4-6 (A = S/n per stream count) and Figure 12's data
(per-stage delays vs stream count) on this machine with the paper's clips. A thin caller of
``dcuscope capacity``, which does the experiment: run that on your own configs.

    benchmarks/streams_sweep --quick --model ssd      # 3982 kbit/s, 30 fps, 1-2 streams, 8 s per count
    benchmarks/streams_sweep --model ssd --rates 30 --bitrates 4971 --max-streams 3 \\
        --kinds file,rtsp,rtsp-late --duration 15 --warmup 5 --plot build/streams_sweep.png

It makes 1920x1080 (``--size``) H.264 clips at each rate and bitrate from the shipped vtest.avi
and bikes.mp4 (cached in build/sweep-clips/; one that cannot be made stops the sweep with one
line, exit status 2), and writes one config per series (kind, rate, bitrate) beside ``--out``
(OUT-KIND-FPS-BITRATE.yaml): the clips as sources (capacity cycles them: stream i plays clip
i % 2), mux -> infer (``--model``) -> tiler -> convert -> osd -> fakesink. Kinds: ``file`` (the
clips played in real time), ``rtsp`` (served on loopback: capacity ``--rtsp``), ``rtsp-late``
(the same, with the mux's max-latency at ``--late-ms``: it drops older frames instead of
batching them). Each series is ``dcuscope capacity CONFIG --json -o OUT-KIND-FPS-BITRATE.json``
(1, 2, ... streams until the slowest keeps under 90 % of the clip's rate, or ``--max-streams``;
its progress on stderr); ``--plot STEM.png`` adds its plot, STEM-KIND-FPS-BITRATE.png. The
documents are assembled into Markdown like the paper's (a table per bitrate, and the per-stage
table) on stdout and in ``--out``.

Gone with issue 49: ``--repeat`` (capacity's 95 % intervals say how far a figure holds),
``--frames``, ``--bitrates-at``, ``--keep-traces`` (run capacity on a written
config) and the OpenCV plot (capacity draws with matplotlib).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.figures import NA, CannotRun, Notes, run  # noqa: E402
from dcuscope.capacity.report import limiting  # noqa: E402

MEDIA = ROOT / "assets" / "media"
MODELS = {"centernet": ROOT / "assets" / "models" / "centernet_mobilenetv3_coco80.onnx",
          "ssd": ROOT / "assets" / "models" / "ssdlite_mobilenetv2_person.onnx"}
CLIP_SOURCES = ("vtest.avi", "bikes.mp4")
"""Stream i plays a clip made from CLIP_SOURCES[i % 2]."""
KINDS = ("file", "rtsp", "rtsp-late")
DEFAULT_LATE_MS = 200
"""rtsp-late's max-latency: 6 frame periods at 30 fps. A live pipeline that keeps up holds a frame
far less than that before the mux, one that falls behind builds a backlog of seconds."""
BITRATES = (3982, 4971, 7955)
"""kbit/s of the paper's clips; its Tables 4, 5 and 6."""
RATES = (30, 60)
STAGES = ("mux", "infer", "tiler", "convert", "osd")
WIDTH, HEIGHT = 1920, 1080
DEFAULT_CACHE = ROOT / "build" / "sweep-clips"
DEFAULT_OUT = ROOT / "build" / "streams_sweep.md"
DEFAULT_PRESET = "superfast"  # x264: quick to make on 2 cores; the bitrate is what the paper fixes


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
        size = f"{self.height}p" if self.width * 9 == self.height * 16 else f"{self.width}x{self.height}p"
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
def config_text(kind: str, clips: list[Path], fps: int, model: str, late_ms: int = DEFAULT_LATE_MS,
                size: tuple[int, int] = (WIDTH, HEIGHT)) -> str:
    """The config of one series: the paper's chain over the ``clips`` (capacity replicates them,
    sets the mux's batch-size to the stream count and widens the tiler's grid); for the RTSP kinds
    the mux waits one frame period for a batch, and rtsp-late drops frames older than ``late_ms``."""
    width, height = size
    # Paths, not file:// URIs, quoted as JSON (valid YAML): the config reader takes a URI's %20 literally.
    sources = "\n".join(f"  - {{uri: {json.dumps(str(c))}, loop: true}}" for c in clips)
    mux = f"batch-size: 1, width: {width}, height: {height}"
    if kind != "file":  # nvstreammux's advice: batched-push-timeout = one frame period of the fastest source
        mux += f", batched-push-timeout: {1_000_000 // fps}" + (f", max-latency: {late_ms}" if kind == "rtsp-late" else "")
    return f"""\
node: sweep
sources:
{sources}
stages:
  - mux: {{{mux}}}
  - infer: {{model: {json.dumps(str(MODELS[model]))}, threshold: 0.3}}
  - tiler: {{rows: 1, columns: 1, width: {width}, height: {height}}}
  - convert: {{format: RGBA}}
  - osd: {{line-width: 3}}
sink: {{type: fake}}
"""


def series(kinds, rates, bitrates) -> list[tuple[str, int, int]]:
    """(kind, fps, bitrate) of every series, bitrate-major."""
    return [(k, f, b) for b in bitrates for k in kinds for f in rates]


def capacity_command(config: Path, kind: str, args: argparse.Namespace, report: Path, plot: Path | None,
                     bitrate: int = BITRATES[0]) -> list[str]:
    """The capacity run of one series; RTSP streams are served at the series' bitrate."""
    return ([sys.executable, "-m", "dcuscope.cli", "capacity", str(config), "--max-streams", str(args.max_streams),
             "--duration", f"{args.duration:g}", "--warmup", f"{args.warmup:g}", "--json", "-o", str(report)]
            + (["--rtsp", "--rtsp-bitrate", str(bitrate)] if kind != "file" else [])
            + (["--all-streams"] if args.all_streams else []) + (["--plot", str(plot)] if plot else []))


# -- report (pure) -----------------------------------------------------------------------------
def _value(estimate: dict | None):
    return estimate["value"] if estimate else None


def _cell(count: dict | None, notes: Notes) -> str:
    """A as "40.0 (p95 60) @ 30.0", * when the count did not keep 90 % of the clip's rate; – not run."""
    if count is None:
        return "–"
    f = count.get("figures")
    if not f or not f["e2e"]:
        return notes.cell(NA(count.get("error") or "no complete frame after the warm-up"))
    p95 = notes.cell(_value(f["e2e"].get("p95")), ".0f", why="no p95 of the frame delay")
    mark = {"holds": "", "fails": "*"}.get(count["outcome"], "?")
    return f"{f['e2e']['mean']['value']:.1f} (p95 {p95}) @ {f['fps_mean']:.1f}{mark}"


def _split(stage: dict | None, name: str, notes: Notes) -> str:
    if stage and stage.get("service") is not None:
        return f"{stage['service']:.1f}/{stage['wait']:.1f}"
    return notes.cell(stage and stage.get("delay"), ".1f", why=f"no frame passed {name} after the warm-up")


def _limit(neck: dict | None, notes: Notes) -> str:
    if not neck:
        return notes.cell(NA("no stage had a delay after the warm-up: no limiting stage"))
    if neck["utilization"] is None:
        return f"{neck['stage']} " + notes.cell(NA("no service times in the trace: the utilization is unknown"))
    return limiting(neck)


def _dropped(f: dict) -> str:
    total = sum(f["dropped"].values())
    if not total:
        return "0"
    share = f", {total / f['delivered']:.0%}" if f["delivered"] else ""
    return ", ".join(f"{reason} {n}" for reason, n in f["dropped"].items()) + f" ({total}{share})"


def markdown(docs: dict[tuple[str, int, int], dict], model: str, preamble: list[str] = ()) -> str:
    """Tables 4-6 (one per bitrate) and Figure 12's per-stage data from the capacity documents of
    the series (``(kind, fps, bitrate) -> document``), after ``preamble`` lines."""
    notes, out = Notes(), [*preamble, ""] if preamble else []
    counts = {(*key, c["streams"]): c for key, doc in docs.items() for c in doc["counts"]}
    columns = [(k, f) for k in KINDS for f in sorted({f for _, f, _ in docs}) if any(s[:2] == (k, f) for s in docs)]
    paper = {b: f"Table {4 + i}" for i, b in enumerate(BITRATES)}
    for bitrate in sorted({b for _, _, b in docs}):
        title = f"{bitrate} kbit/s" + (f" (paper's {paper[bitrate]})" if bitrate in paper else "")
        out += [f"#### A = S/n per stream count, {title}, model {model}", "",
                "| streams | " + " | ".join(f"{k} {f} fps" for k, f in columns) + " |", "|---:|" + "---:|" * len(columns)]
        for n in sorted({s for (_, _, b, s) in counts if b == bitrate}):
            out.append(f"| {n} | " + " | ".join(_cell(counts.get((k, f, bitrate, n)), notes) for k, f in columns) + " |")
        out.append("")
    out += ["Cells: A = S/n, the mean frame delay in ms (p95 in ms) @ frames/s per stream (the mean over the "
            "streams); * the slowest stream kept under 90 % of the clip's rate, ? undecided (capacity's 95 % "
            "interval straddles 90 %); – not run (a series stops at its first count marked * or ?).", "",
            f"#### Per-stage mean service/wait (ms), Figure 12's data, model {model}", "",
            "| input | fps | kbit/s | streams | limiting stage | " + " | ".join(STAGES)
            + " | between | A | p95 | fps/stream | dropped | CPU cores | serve-rtsp cores |",
            "|---|---:|---:|---:|---|" + "---:|" * (len(STAGES) + 7)]
    for (kind, fps, bitrate, n), c in sorted(counts.items(), key=lambda kv: (KINDS.index(kv[0][0]), *kv[0][1:])):
        f = c.get("figures")
        if not f or not f["e2e"]:
            continue
        stages = " | ".join(_split(f["stages"].get(s), s, notes) for s in STAGES)
        cores = "–" if c.get("server_cores") is None else f"{c['server_cores']:.2f}"
        out.append(f"| {kind} | {fps} | {bitrate} | {n} | {_limit(c['limiting'], notes)} | {stages} | "
                   f"{notes.cell(f['between_ms'], '.1f')} | {f['e2e']['mean']['value']:.1f} | "
                   f"{notes.cell(_value(f['e2e'].get('p95')), '.1f', why='no p95 of the frame delay')} | "
                   f"{f['fps_mean']:.1f}{'*' if c['outcome'] == 'fails' else ''} | {_dropped(f)} | "
                   f"{notes.cell(c.get('cpu_cores'), '.2f')} | {cores} |")
    out += ["", "Stage cells: mean service/wait in ms (delay = service + wait: the stage's own work on the buffer "
            "that carried the frame out, and time queued, waiting for a batch or blocked downstream). limiting "
            "stage: the bottleneck with its utilization (busy fraction of the run), its streaming thread's when "
            "stages share it, sat. when that thread is saturated. between = A minus the stage delays. dropped: "
            "frames dropped after the warm-up by reason (late: older than the mux's max-latency), their total and "
            "share of the frames decoded. CPU cores: the pipeline's process; serve-rtsp cores: the RTSP server's, "
            "which decodes and re-encodes every stream on this same machine."]
    failed = [(key, c) for key, c in counts.items() if c.get("error")]
    answers = [f"- {k} {f} fps {b} kbit/s: {doc['answer']}" for (k, f, b), doc in docs.items() if doc.get("answer")]
    if failed or notes or answers:
        out += ["", "Notes:"] + [f"- {line}" for line in notes.lines()] + answers + [
            f"- {k} {f} fps {b} kbit/s {n} stream(s): {c['error']}" for (k, f, b, n), c in failed]
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


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="one bitrate (3982), 30 fps only, at most 2 streams; "
                                                        "8 s counts with 3 s of warm-up unless given")
    p.add_argument("--model", choices=sorted(MODELS), default="centernet",
                   help="detector: centernet (80 classes, the product's default) or ssd (persons, much faster)")
    p.add_argument("--kinds", type=lambda t: t.split(","), default=list(KINDS[:2]),
                   help="input kinds, of file, rtsp and rtsp-late (default file,rtsp)")
    p.add_argument("--late-ms", type=int, default=DEFAULT_LATE_MS, help="the mux's max-latency of rtsp-late, ms "
                                                                       f"(default {DEFAULT_LATE_MS})")
    p.add_argument("--rates", type=_ints, default=list(RATES), help="clip frame rates (default 30,60)")
    p.add_argument("--bitrates", type=_ints, default=list(BITRATES), help="clip bitrates, kbit/s (default 3982,4971,7955)")
    p.add_argument("--max-streams", type=int, default=4, help="highest stream count (default 4)")
    p.add_argument("--all-streams", action="store_true", help="every count up to --max-streams, past the first that "
                                                              "does not keep 90 %% of the rate (capacity --all-streams)")
    p.add_argument("--duration", type=float, help="seconds per stream count (default 20)")
    p.add_argument("--warmup", type=float, help="seconds of frames left out at the start of each (default 5)")
    p.add_argument("--clip-seconds", type=int, default=10, help="length of the clips made (default 10)")
    p.add_argument("--size", type=_size, default=(WIDTH, HEIGHT), metavar="WxH",
                   help=f"frame size of the clips, the mux and the collage (default {WIDTH}x{HEIGHT}, the paper's)")
    p.add_argument("--preset", default=DEFAULT_PRESET, help=f"x264 speed-preset of the clips (default {DEFAULT_PRESET})")
    p.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="clip folder (default build/sweep-clips)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Markdown results (default build/streams_sweep.md); "
                   "each series' config and capacity document beside it (OUT-KIND-FPS-BITRATE.yaml, .json)")
    p.add_argument("--plot", type=Path, metavar="STEM.png", help="capacity's plot of each series: "
                   "STEM-KIND-FPS-BITRATE.png (needs matplotlib)")
    args = p.parse_args(argv)
    quick = args.quick
    if quick:
        args.bitrates, args.rates, args.max_streams = args.bitrates[:1], [30], min(args.max_streams, 2)
    args.duration = args.duration if args.duration is not None else 8.0 if quick else 20.0
    args.warmup = args.warmup if args.warmup is not None else 3.0 if quick else 5.0
    bad = [k for k in args.kinds if k not in KINDS]
    if bad or args.max_streams < 1 or args.late_ms < 1 or not 0 <= args.warmup < args.duration:
        p.error(f"unknown kinds {bad} (known: {', '.join(KINDS)})" if bad else
                "need --max-streams >= 1, --late-ms >= 1 and 0 <= --warmup < --duration")
    return args


def machine() -> str:
    """CPU count and model, and load: the figures only mean something next to these."""
    try:
        model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith("model name"))
    except (OSError, StopIteration):
        model = "?"
    return f"{os.cpu_count()} CPUs ({model}), load average {', '.join(f'{x:.1f}' for x in os.getloadavg())}"


def main(argv: list[str] | None = None) -> int:
    from dcuscope.core.gst import GLib

    args = parse_args(argv)
    started = time.monotonic()

    def log(line: str) -> None:
        print(f"sweep [{time.monotonic() - started:4.0f} s] {line}", file=sys.stderr, flush=True)

    plan = series(args.kinds, args.rates, args.bitrates)
    streams = min(args.max_streams, len(CLIP_SOURCES))
    for fps, bitrate in dict.fromkeys((f, b) for _, f, b in plan):
        for i in range(streams):
            spec = clip_for(i, fps, bitrate, args.clip_seconds, args.preset, args.size)
            if not (args.cache / spec.name).is_file():
                log(f"making the clip {spec.name}")
            try:
                make_clip(spec, args.cache, progress=log)
            except (RuntimeError, OSError, GLib.Error) as exc:  # GLib.Error: an element of its pipeline is missing
                raise CannotRun(f"cannot make the clip {spec.name}: {getattr(exc, 'message', exc)}") from exc

    command = " ".join(["benchmarks/streams_sweep", *(sys.argv[1:] if argv is None else argv)])
    preamble = [f"- command: `{command}`", f"- date: {time.strftime('%Y-%m-%d %H:%M %Z')}",
                f"- machine at the start: {machine()}",
                f"- `dcuscope capacity` per series: {args.duration:g} s per stream count, first {args.warmup:g} s of "
                f"frames left out; clips {args.size[0]}x{args.size[1]}, {args.clip_seconds} s, x264 {args.preset}, "
                f"looped; model {args.model}" + (f"; rtsp-late: max-latency {args.late_ms} ms" if "rtsp-late" in args.kinds else "")]
    for folder in {args.out.parent, (args.plot or args.out).parent}:
        folder.mkdir(parents=True, exist_ok=True)
    docs, status = {}, 0
    for n, (kind, fps, bitrate) in enumerate(plan, 1):
        stem = args.out.with_name(f"{args.out.stem}-{kind}-{fps}-{bitrate}")
        config, report = stem.with_suffix(".yaml"), stem.with_suffix(".json")
        clips = [args.cache / clip_for(i, fps, bitrate, args.clip_seconds, args.preset, args.size).name
                 for i in range(streams)]
        config.write_text(config_text(kind, clips, fps, args.model, args.late_ms, args.size))
        report.unlink(missing_ok=True)
        plot = args.plot and args.plot.with_name(f"{args.plot.stem}-{kind}-{fps}-{bitrate}{args.plot.suffix or '.png'}")
        log(f"[series {n}/{len(plan)}] {kind} {fps} fps {bitrate} kbit/s: dcuscope capacity {config.name}")
        proc = subprocess.Popen(capacity_command(config, kind, args, report, plot, bitrate), cwd=ROOT, stdout=subprocess.DEVNULL,
                                env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])})
        try:
            code = proc.wait()
        except KeyboardInterrupt:  # capacity got the Ctrl-C too: it stops and writes what it measured
            code = proc.wait()
        doc = docs[(kind, fps, bitrate)] = json.loads(report.read_text()) if report.is_file() else {
            "counts": [], "answer": f"nothing measured: dcuscope capacity ended with status {code} (its reason above)"}
        if code == 2:  # bad input (e.g. --plot without matplotlib): the same for every series
            raise CannotRun(f"dcuscope capacity refused {config} (its reason above)")
        if code == 130:
            status = 130
            log("stopped by Ctrl-C")
            break
        # 1: a count without figures (capacity said why above); an undecided one is a result ("?").
        status = max(status, int(code not in (0, 1) or not doc["counts"] or any(c["error"] for c in doc["counts"])))
        args.out.write_text(markdown(docs, args.model, preamble))  # after every series: an interruption keeps them
    text = markdown(docs, args.model, preamble + [f"- machine at the end: {machine()}"])
    args.out.write_text(text)
    print(text, end="")
    log(f"done: {args.out}")
    return status


if __name__ == "__main__":
    sys.exit(run(main))
