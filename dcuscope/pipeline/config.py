"""The YAML pipeline configuration as typed objects.

A configuration names its sources, the chain of stages they go through, and a sink::

    node: DCU-1                     # optional: name of this machine in traces and the relay
    sources:
      - uri: ../assets/media/vtest.avi   # file path (relative to this file), file://, rtsp://, http://
        loop: true                  # files: start again at the end
        live: true                  # files and tests: frames in real time, like a camera
        rate: 10                    # optional frames/s (videorate)
        width: 960                  # optional size before the mux (videoscale)
        height: 540
      - test: ball                  # a videotestsrc pattern
      - camera: /dev/video0         # a V4L2 device
        stall-timeout: 3            # live sources: report a stall after this many s without a frame
      - uri: rtsp://10.0.0.5/cam1
        latency: 200                # RTSP only: rtspsrc's jitter buffer, ms (default 2000)
    stages:
      - mux: {batch-size: 2, width: 1280, height: 720}
      - infer: {threshold: 0.3}
      - factory: identity           # any installed GStreamer element, by factory name
        name: slow
        properties: {sleep-time: 20000}
      - queue: {}
      - tiler: {rows: 1, columns: 2}
      - convert: {format: RGBA}
      - osd: {}
    sink: {type: file, path: out.mp4}   # fake | file (H.264 in .mp4, .mkv, .avi) | frames (numbered PNGs) | rtsp
    probes: {enabled: false, clock: realtime, trace: trace.jsonl, trigger: hooks}   # trigger: hooks | probes

Several outputs at once (DeepStream's display + file + RTSP out): ``sinks:``, a list of the same
entries, fed through a ``tee`` (each branch behind a queue of its own, so that a slow output
does not hold the others)::

    sinks:
      - {type: file, path: out.mp4}
      - {type: rtsp, port: 8555, mount: /out}   # served with GstRtspServer: rtsp://127.0.0.1:8555/out
      - {type: fake, name: measure}

Any graph the structured form cannot say is one ``launch:`` line in gst-launch syntax, with
dcuscope's elements available (``pipeline.launch``): it replaces sources, stages and sinks.

This module checks the structure (keys, types, files); :mod:`dcuscope.pipeline.elements` checks the
stages, and the source and sink values that become element properties, against the installed
GStreamer elements and their property specs, before the pipeline is built.

The objects are frozen: once checked, a configuration is not changed by whoever uses it. A
command-line override makes a new one (``dataclasses.replace``); building a pipeline returns
what it resolved (:class:`dcuscope.pipeline.build.BuiltPipeline`) instead of writing it back here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

from dcuscope.pipeline.yamlsource import Document, KeyPath, load_document

STAGE_SHORTHANDS = ("mux", "infer", "tiler", "convert", "osd", "queue")
"""Stage kinds written as ``- KIND: {properties}``; anything else is ``- factory: NAME``."""
SINK_TYPES = ("fake", "file", "frames", "rtsp", "rtp", "shm")
RTP_ENCODINGS = ("H264", "H265", "JPEG")
"""What an ``rtp:`` source can receive (its depayloader: rtph264depay, rtph265depay, rtpjpegdepay)."""
SHM_FORMAT = "I420"
"""The pixel format a ``shm`` sink writes and a ``shm:`` source reads unless told (``format:``)."""
DEFAULT_RTSP_PORT = 8554
DEFAULT_RTSP_MOUNT = "/dcuscope"
CLOCK_NAMES = ("realtime", "tai", "monotonic")
DEFAULT_STALL_TIMEOUT_S = 3.0
REMOTE_SCHEMES = ("rtsp://", "rtsps://", "http://", "https://", "udp://", "rtmp://", "srt://")


@dataclass(frozen=True)
class SourceConfig:
    kind: str
    """``uri``, ``camera``, ``test``, ``rtp`` (RTP from another pipeline) or ``shm`` (shared memory
    from another pipeline: docs/journeys.md)."""
    location: str
    """A URI (local files as absolute ``file://``), a device path, a test pattern name, the UDP port
    RTP arrives on, or the shared memory's socket path."""
    loop: bool = False
    """Files only: seek back to the start at the end, forever."""
    rate: Fraction | None = None
    """Frames per second forced with videorate; None keeps the stream's own rate."""
    width: int | None = None
    height: int | None = None
    """Size forced before the mux; None keeps the stream's own (the mux scales to its size)."""
    live: bool = False
    """Files and test sources: frames come in real time, like a camera's (files: clocksync paces
    them), whether or not the pipeline keeps up; without it they come as fast as it takes them."""
    stall_timeout: float = DEFAULT_STALL_TIMEOUT_S
    """Live sources: seconds without a frame (while the others go on) before a stall is reported; 0: never."""
    latency_ms: int | None = None
    """RTSP and RTP sources: the jitter buffer's latency; None keeps rtspsrc's default (2000 ms),
    rtpjitterbuffer's (200 ms)."""
    encoding: str = "H264"
    """RTP sources: what the packets carry (:data:`RTP_ENCODINGS`)."""
    format: str = SHM_FORMAT
    """Shared-memory sources: the frames' pixel format (the sender's caps)."""

    @property
    def is_live(self) -> bool:
        """Frames come in real time whether or not the pipeline is ready: cameras, streams, live tests."""
        return self.kind in ("camera", "rtp", "shm") or self.live or self.location.startswith(REMOTE_SCHEMES)

    @property
    def description(self) -> str:
        return f"{self.kind}:{self.location}"


@dataclass(frozen=True)
class StageConfig:
    factory: str
    """GStreamer element factory name (``mux``, ``infer``, ``identity``, ...)."""
    name: str
    """Element (and stage) name: the ``name`` given, else the factory, made unique with ``_N``."""
    properties: Mapping[str, Any]
    """As written in the YAML (read-only)."""
    path: KeyPath
    """Where the stage is in the YAML, for error messages."""


@dataclass(frozen=True)
class SinkConfig:
    kind: str = "fake"
    path: Path | None = None
    """``file``: the video to write (its suffix names the container); ``frames``: a folder for numbered PNGs."""
    sync: bool = False
    """Render at the stream's pace (True) or as fast as the pipeline goes (False)."""
    bitrate: int = 4000
    """``file`` and ``rtsp``: H.264 bitrate in kbit/s."""
    name: str = "sink"
    """The sink's stage name: ``sink`` for the one ``sink:``; in ``sinks:`` the ``name`` given,
    else the type, made unique with ``_N``."""
    host: str = "127.0.0.1"
    port: int = DEFAULT_RTSP_PORT
    mount: str = DEFAULT_RTSP_MOUNT
    """``rtsp``: served at rtsp://HOST:PORT/MOUNT; ``rtp``: H.264 over RTP sent to HOST:PORT (UDP)."""

    @property
    def url(self) -> str:
        return f"rtsp://{self.host}:{self.port}{self.mount}"


TRIGGERS = ("hooks", "probes")


@dataclass(frozen=True)
class ProbesConfig:
    enabled: bool = False
    clock: str = "realtime"
    trace: Path | None = None
    trigger: str = "hooks"
    """What fires the native tracepoints: the dcuscope tracer's hooks, or pad probes (docs/probes.md)."""


@dataclass(frozen=True)
class PipelineConfig:
    file: Path
    node: str
    sources: tuple[SourceConfig, ...]
    stages: tuple[StageConfig, ...]
    sinks: tuple[SinkConfig, ...]
    """One, or several fed through a tee."""
    probes: ProbesConfig
    document: Document = field(repr=False)
    launch: str | None = None
    """A ``launch:`` pipeline (gst-launch syntax): then sources and stages are empty."""

    @property
    def sink(self) -> SinkConfig:
        """The first (often the only) sink."""
        return self.sinks[0]


def load_config(file: str | Path) -> PipelineConfig:
    """Read and check ``file``: raises ConfigError naming file:line and key path."""
    file = Path(file)
    doc = load_document(file)
    return _Parser(doc).parse()


class _Parser:
    def __init__(self, doc: Document):
        self.doc = doc
        self.base = doc.file.resolve().parent

    def parse(self) -> PipelineConfig:
        top = self.mapping(self.doc.data, (), {"node", "sources", "stages", "sink", "sinks", "probes", "name",
                                               "launch"})
        if "launch" in top:
            return self.launch(top)
        if "sources" not in top:
            raise self.doc.error((), "missing 'sources' (a list of uri:/camera:/test: entries)")
        if "stages" not in top:
            raise self.doc.error((), "missing 'stages' (the chain mux, infer, tiler, convert, osd)")
        sources = tuple(self.source(s, ("sources", i)) for i, s in enumerate(self.sequence(top["sources"], ("sources",))))
        if not sources:
            raise self.doc.error(("sources",), "at least one source is needed")
        stages = self.stages(self.sequence(top["stages"], ("stages",)))
        return PipelineConfig(
            file=self.doc.file,
            node=self.text(top.get("node", "DCU-1"), ("node",)),
            sources=sources,
            stages=stages,
            sinks=self.sinks(top),
            probes=self.probes(top.get("probes", {})),
            document=self.doc,
        )

    def launch(self, top: dict) -> PipelineConfig:
        for key in ("sources", "stages", "sink", "sinks"):
            if key in top:
                raise self.doc.error((key,), "a launch: pipeline says its sources, stages and sinks itself: "
                                             f"remove {key}: (or launch:)")
        text = self.text(top["launch"], ("launch",)).strip()
        return PipelineConfig(file=self.doc.file, node=self.text(top.get("node", "DCU-1"), ("node",)), sources=(),
                              stages=(), sinks=(SinkConfig(kind="launch", name=""),),
                              probes=self.probes(top.get("probes", {})), document=self.doc, launch=text)

    def sinks(self, top: dict) -> tuple[SinkConfig, ...]:
        if "sink" in top and "sinks" in top:
            raise self.doc.error(("sinks",), "give either sink: (one output) or sinks: (a list), not both")
        if "sinks" not in top:
            return (self.sink(top.get("sink", {"type": "fake"}), ("sink",), "sink"),)
        entries = self.sequence(top["sinks"], ("sinks",))
        if not entries:
            raise self.doc.error(("sinks",), "at least one sink is needed")
        sinks, seen, ports = [], {}, {}
        for i, entry in enumerate(entries):
            sink = self.sink(entry, ("sinks", i), None)
            name = sink.name
            seen[name] = seen.get(name, -1) + 1
            if seen[name]:
                name = f"{name}_{seen[name]}"
            if sink.kind == "rtsp":
                if (sink.host, sink.port) in ports and ports[(sink.host, sink.port)] == sink.mount:
                    raise self.doc.error(("sinks", i, "mount"), f"{sink.url} is served twice")
                ports[(sink.host, sink.port)] = sink.mount
            sinks.append(replace(sink, name=name))
        return tuple(sinks)

    # -- typed getters -------------------------------------------------------------------
    def mapping(self, value: Any, path: KeyPath, allowed: set[str]) -> dict:
        if not isinstance(value, dict):
            raise self.doc.error(path, f"expected a mapping, got {_kind(value)}")
        for key in value:
            if key not in allowed:
                raise self.doc.error(path + (key,), f"unknown key (expected one of: {', '.join(sorted(allowed))})")
        return value

    def sequence(self, value: Any, path: KeyPath) -> list:
        if not isinstance(value, list):
            raise self.doc.error(path, f"expected a list, got {_kind(value)}")
        return value

    def text(self, value: Any, path: KeyPath) -> str:
        if not isinstance(value, str) or not value:
            raise self.doc.error(path, f"expected text, got {_kind(value)}")
        return value

    def boolean(self, value: Any, path: KeyPath) -> bool:
        if not isinstance(value, bool):
            raise self.doc.error(path, f"expected true or false, got {_kind(value)}")
        return value

    def positive_int(self, value: Any, path: KeyPath) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise self.doc.error(path, f"expected a positive integer, got {_kind(value)}")
        return value

    def non_negative_int(self, value: Any, path: KeyPath) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise self.doc.error(path, f"expected an integer >= 0, got {_kind(value)}")
        return value

    def seconds(self, value: Any, path: KeyPath) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < 1e6:
            raise self.doc.error(path, f"expected seconds >= 0 (0: off), got {_kind(value)}")
        return float(value)

    def rate(self, value: Any, path: KeyPath) -> Fraction:
        try:
            rate = Fraction(str(value)) if not isinstance(value, bool) else None
        except (ValueError, ZeroDivisionError):
            rate = None
        if rate is None or rate <= 0:
            raise self.doc.error(path, f"expected frames per second such as 30 or 30000/1001, got {value!r}")
        return rate

    def local_file(self, value: str, path: KeyPath, what: str) -> Path:
        file = Path(value).expanduser()
        file = file if file.is_absolute() else (self.base / file)
        if not file.is_file():
            raise self.doc.error(path, f"{what} not found: {file}")
        return file.resolve()

    # -- sections ------------------------------------------------------------------------
    def source(self, value: Any, path: KeyPath) -> SourceConfig:
        entry = self.mapping(value, path, {"uri", "camera", "test", "rtp", "shm", "loop", "rate", "width", "height",
                                           "live", "stall-timeout", "latency", "encoding", "format"})
        kinds = [k for k in ("uri", "camera", "test", "rtp", "shm") if k in entry]
        if len(kinds) != 1:
            raise self.doc.error(path, "a source needs exactly one of uri:, camera:, test:, rtp:, shm:")
        kind = kinds[0]
        if kind == "rtp":
            port = self.positive_int(entry[kind], path + (kind,))
            if port > 65535:
                raise self.doc.error(path + (kind,), f"expected the UDP port RTP arrives on, 1..65535, got {port}")
            location = str(port)
        else:
            location = self.text(entry[kind], path + (kind,))
        fields: dict[str, Any] = {}
        if "encoding" in entry:
            if kind != "rtp":
                raise self.doc.error(path + ("encoding",), "only rtp: sources take encoding:")
            fields["encoding"] = self.text(entry["encoding"], path + ("encoding",)).upper()
            if fields["encoding"] not in RTP_ENCODINGS:
                raise self.doc.error(path + ("encoding",), f"expected one of: {', '.join(RTP_ENCODINGS)}")
        if "format" in entry:
            if kind != "shm":
                raise self.doc.error(path + ("format",), "only shm: sources take format:")
            fields["format"] = self.text(entry["format"], path + ("format",))
        if kind == "shm":
            missing = [k for k in ("width", "height", "rate") if k not in entry]
            if missing:
                raise self.doc.error(path, f"a shm: source needs the sender's {', '.join(missing)} (shared memory "
                                           "carries bytes, not caps)")
            socket = Path(location).expanduser()
            location = str(socket if socket.is_absolute() else self.base / socket)
        if kind == "uri":
            location = self.uri(location, path + (kind,))
        elif kind == "camera" and not Path(location).exists():
            raise self.doc.error(path + (kind,), f"camera device not found: {location}")
        if "loop" in entry:
            fields["loop"] = self.boolean(entry["loop"], path + ("loop",))
            if fields["loop"] and not location.startswith("file://"):
                raise self.doc.error(path + ("loop",), "only files can loop")
        if "live" in entry:
            fields["live"] = self.boolean(entry["live"], path + ("live",))
            if kind in ("camera", "rtp", "shm") or (kind == "uri" and not location.startswith("file://")):
                raise self.doc.error(path + ("live",), "only files and test sources take live: (cameras and streams are live)")
        if "rate" in entry:
            fields["rate"] = self.rate(entry["rate"], path + ("rate",))
        for key in ("width", "height"):
            if key in entry:
                fields[key] = self.positive_int(entry[key], path + (key,))
        if "stall-timeout" in entry:
            fields["stall_timeout"] = self.seconds(entry["stall-timeout"], path + ("stall-timeout",))
        if "latency" in entry:
            if kind != "rtp" and not location.startswith(("rtsp://", "rtsps://")):
                raise self.doc.error(path + ("latency",), "only rtsp:// and rtp: sources take latency:")
            fields["latency_ms"] = self.non_negative_int(entry["latency"], path + ("latency",))
        return SourceConfig(kind=kind, location=location, **fields)

    def uri(self, value: str, path: KeyPath) -> str:
        if value.startswith(REMOTE_SCHEMES):
            return value
        if value.startswith("file://"):
            value = value[len("file://"):]
        elif "://" in value:
            raise self.doc.error(path, f"unsupported URI scheme in {value!r} (file, rtsp, http(s), udp, rtmp, srt)")
        return self.local_file(value, path, "video file").as_uri()

    def stages(self, entries: list) -> tuple[StageConfig, ...]:
        stages, seen = [], {}
        for i, value in enumerate(entries):
            path = ("stages", i)
            if not isinstance(value, dict) or not value:
                raise self.doc.error(path, f"expected '- KIND: {{properties}}' or '- factory: NAME', got {_kind(value)}")
            if "factory" in value:
                entry = self.mapping(value, path, {"factory", "name", "properties"})
                factory = self.text(entry["factory"], path + ("factory",))
                props_path = path + ("properties",)
                props = entry.get("properties", {}) or {}
                name = self.text(entry["name"], path + ("name",)) if "name" in entry else None
            else:
                if len(value) != 1:
                    raise self.doc.error(path, "a stage is one '- KIND: {properties}' entry, or use factory:/name:/properties:")
                (factory, props), = value.items()
                if factory not in STAGE_SHORTHANDS:
                    raise self.doc.error(path + (factory,),
                                         f"unknown stage kind (expected one of: {', '.join(STAGE_SHORTHANDS)}; "
                                         "other elements: '- factory: NAME')")
                props_path = path + (factory,)
                props = props or {}
                name = props.get("name") if isinstance(props, dict) else None
                if name is not None:  # a copy without it: the YAML data stays as read
                    props = {key: value for key, value in props.items() if key != "name"}
            if not isinstance(props, dict):
                raise self.doc.error(props_path, f"expected a mapping of properties, got {_kind(props)}")
            name = name or factory
            if name in seen:  # unique names, Savant-style: infer, infer_1, ...
                seen[name] += 1
                name = f"{name}_{seen[name]}"
            else:
                seen[name] = 0
            stages.append(StageConfig(factory=factory, name=name, properties=MappingProxyType(dict(props)),
                                      path=props_path))
        if not stages:
            raise self.doc.error(("stages",), "at least one stage is needed")
        return tuple(stages)

    def sink(self, value: Any, path: KeyPath, name: str | None) -> SinkConfig:
        entry = self.mapping(value, path, {"type", "path", "sync", "bitrate", "name", "host", "port", "mount"})
        kind = self.text(entry.get("type", "fake"), path + ("type",))
        if kind not in SINK_TYPES:
            raise self.doc.error(path + ("type",), f"unknown sink type {kind!r} (expected one of: {', '.join(SINK_TYPES)})")
        fields: dict[str, Any] = {"name": name or kind}
        if "name" in entry:
            if name is not None:
                raise self.doc.error(path + ("name",), "the one sink: is the stage 'sink'; names are for sinks: entries")
            fields["name"] = self.text(entry["name"], path + ("name",))
        if kind in ("file", "frames", "shm"):
            if "path" not in entry:
                raise self.doc.error(path, f"sink type {kind} needs a path:" + (" (the socket shmsrc connects to)"
                                                                               if kind == "shm" else ""))
            target = Path(self.text(entry["path"], path + ("path",))).expanduser()
            fields["path"] = target if target.is_absolute() else Path.cwd() / target
        for key in ("host", "port", "mount"):
            if key in entry and kind not in ("rtsp", "rtp") or key == "mount" and key in entry and kind == "rtp":
                raise self.doc.error(path + (key,), f"only {'rtsp' if key == 'mount' else 'rtsp and rtp'} sinks take "
                                                    f"{key}:")
        if kind == "rtp" and "port" not in entry:
            raise self.doc.error(path, "sink type rtp needs the port: it sends to (and host:, default 127.0.0.1)")
        if "host" in entry:
            fields["host"] = self.text(entry["host"], path + ("host",))
        if "port" in entry:
            fields["port"] = self.positive_int(entry["port"], path + ("port",))
            if fields["port"] > 65535:
                raise self.doc.error(path + ("port",), f"expected a port number 1..65535, got {fields['port']}")
        if "mount" in entry:
            mount = self.text(entry["mount"], path + ("mount",))
            if not mount.startswith("/") or " " in mount:
                raise self.doc.error(path + ("mount",), f"expected a path such as /out, got {mount!r}")
            fields["mount"] = mount
        if "sync" in entry:
            fields["sync"] = self.boolean(entry["sync"], path + ("sync",))
        if "bitrate" in entry:
            fields["bitrate"] = self.positive_int(entry["bitrate"], path + ("bitrate",))
        return SinkConfig(kind=kind, **fields)

    def probes(self, value: Any) -> ProbesConfig:
        path = ("probes",)
        entry = self.mapping(value, path, {"enabled", "clock", "trace", "trigger"})
        fields: dict[str, Any] = {}
        if "enabled" in entry:
            fields["enabled"] = self.boolean(entry["enabled"], path + ("enabled",))
        if "clock" in entry:
            fields["clock"] = self.text(entry["clock"], path + ("clock",))
            if fields["clock"] not in CLOCK_NAMES:
                raise self.doc.error(path + ("clock",), f"unknown clock (expected one of: {', '.join(CLOCK_NAMES)})")
        if "trace" in entry:
            fields["trace"] = Path(self.text(entry["trace"], path + ("trace",)))
        if "trigger" in entry:
            fields["trigger"] = self.text(entry["trigger"], path + ("trigger",))
            if fields["trigger"] not in TRIGGERS:
                raise self.doc.error(path + ("trigger",), f"unknown trigger (expected one of: {', '.join(TRIGGERS)})")
        return ProbesConfig(**fields)


def _kind(value: Any) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"a boolean ({value})"
    if isinstance(value, (int, float)):
        return f"a number ({value})"
    if isinstance(value, str):
        return f"text ({value!r})"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__
