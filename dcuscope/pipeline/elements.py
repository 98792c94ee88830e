"""Stages -> GStreamer elements: factory lookup and property checking against the real pspecs.

Every installed element can be a stage; every value is checked before anything runs, by the
property's GObject spec (booleans, numbers within their range, enums and flags by their known
values, caps and their video formats), and for dcuscope's own text properties that are really
enums by the values the element declares (``CHOICES``). The values that configure the source
and sink elements (a test pattern, an RTSP latency, a bitrate) are checked the same way against
the elements they set. So a typo fails at load time with file:line and the known values, not
mid-stream.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

from dcuscope.core.gst import GObject, Gst, GstVideo
from dcuscope.pipeline.config import PipelineConfig, StageConfig
from dcuscope.pipeline.yamlsource import Document, KeyPath
from dcuscope.plugins.models import ModelError, check_model

FILE_PROPERTIES = {"infer": ("model", "labels")}
"""Properties that name files: resolved against the configuration's folder and checked."""

_INT_TYPES = {GObject.TYPE_INT, GObject.TYPE_UINT, GObject.TYPE_LONG, GObject.TYPE_ULONG,
              GObject.TYPE_INT64, GObject.TYPE_UINT64}
_FLOAT_TYPES = {GObject.TYPE_FLOAT, GObject.TYPE_DOUBLE}


def make_stage_element(config: PipelineConfig, stage: StageConfig) -> Gst.Element:
    """Create ``stage``'s element with its properties set; ConfigError on any problem."""
    doc = config.document
    if Gst.ElementFactory.find(stage.factory) is None:
        raise doc.error(stage.path[:2] + ("factory",), f"no GStreamer element named {stage.factory!r} is installed (see gst-inspect-1.0)")
    element = Gst.ElementFactory.make(stage.factory, stage.name)
    if element is None:
        raise doc.error(stage.path, f"element {stage.factory!r} could not be created")
    for key, value in stage.properties.items():
        set_checked_property(config, stage, element, key, value)
    if stage.factory == "infer":
        _check_model(config, stage, element)
    return element


def check_source_and_sink_values(config: PipelineConfig) -> None:
    """The values of ``sources:`` and ``sinks:`` that become element properties, checked against
    those elements' specs (the elements themselves are made later, by their own modules)."""
    doc = config.document
    for i, source in enumerate(config.sources):
        if source.kind == "test":
            _check_value(doc, ("sources", i, "test"), "videotestsrc", "pattern", source.location)
        if source.latency_ms is not None:
            _check_value(doc, ("sources", i, "latency"), "rtspsrc", "latency", source.latency_ms)
    several = isinstance(doc.data, dict) and "sinks" in doc.data
    for i, sink in enumerate(config.sinks):
        if sink.kind in ("file", "rtsp"):
            where = ("sinks", i) if several else ("sink",)
            _check_value(doc, where + ("bitrate",), "x264enc", "bitrate", sink.bitrate)


def check_launch_choices(doc: Document, path: KeyPath, pipeline: Gst.Bin) -> None:
    """A ``launch:`` line's dcuscope elements: GStreamer parsed their properties by type; the text
    ones that are really enums are checked here, as they are in a stage."""
    for element in pipeline.iterate_recurse():
        for name, known in getattr(type(element), "CHOICES", {}).items():
            value = element.get_property(name)
            if value not in known:
                raise doc.error(path, f"{element.get_name()}.{name}: {_one_of(known, value)}")


def _check_value(doc: Document, path: KeyPath, factory: str, key: str, value: Any) -> None:
    element = _scratch(factory)
    if element is not None:  # a missing element is reported where the pipeline is built, with its package
        _check_and_set(doc, path, element, element.find_property(key), value)


@cache
def _scratch(factory: str) -> Gst.Element | None:
    """One element of ``factory`` to check values on (never linked or started)."""
    return Gst.ElementFactory.make(factory, None)


def _check_model(config: PipelineConfig, stage: StageConfig, element: Gst.Element) -> None:
    """Its model file opens and its layout fits the decoder, now rather than once it runs."""
    try:
        check_model(element.get_property("model"), element.get_property("decoder"))
    except ModelError as exc:
        key = "model" if "model" in stage.properties or "decoder" not in stage.properties else "decoder"
        raise config.document.error(stage.path + (key,), str(exc).splitlines()[0]) from exc


def set_checked_property(config: PipelineConfig, stage: StageConfig, element: Gst.Element, key: str, value: Any) -> None:
    doc = config.document
    path = stage.path + (key,)
    pspec = element.find_property(key)
    if pspec is None or key == "name":
        known = sorted(p.name for p in element.list_properties() if p.flags & GObject.ParamFlags.WRITABLE
                       and p.name not in ("name", "parent"))
        raise doc.error(path, f"unknown property of {stage.factory} (known: {', '.join(known)})")
    if not pspec.flags & GObject.ParamFlags.WRITABLE:
        raise doc.error(path, f"property {key} of {stage.factory} is read-only")
    if key in FILE_PROPERTIES.get(stage.factory, ()):
        value = str(_local_file(config, path, value))
    _check_and_set(doc, path, element, pspec, value)


def _local_file(config: PipelineConfig, path, value: Any) -> Path:
    if not isinstance(value, str) or not value:
        raise config.document.error(path, "expected a file path")
    file = Path(value).expanduser()
    file = file if file.is_absolute() else config.file.resolve().parent / file
    if not file.is_file():
        raise config.document.error(path, f"file not found: {file}")
    return file.resolve()


def _one_of(known, value: Any) -> str:
    return f"expected one of: {', '.join(map(str, known))}; got {value!r}"


def _check_and_set(doc: Document, path: KeyPath, element: Gst.Element, pspec: GObject.ParamSpec, value: Any) -> None:
    vtype = pspec.value_type
    name = pspec.name
    if vtype == GObject.TYPE_BOOLEAN:
        if not isinstance(value, bool):
            raise doc.error(path, f"expected true or false, got {value!r}")
    elif vtype in _INT_TYPES or vtype in _FLOAT_TYPES:
        is_int = vtype in _INT_TYPES
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (is_int and not isinstance(value, int)):
            raise doc.error(path, f"expected {'an integer' if is_int else 'a number'}, got {value!r}")
        lo, hi = getattr(pspec, "minimum", None), getattr(pspec, "maximum", None)
        if lo is not None and hi is not None and not lo <= value <= hi:
            raise doc.error(path, f"{value} is out of range [{lo}, {hi}]")
    elif vtype == GObject.TYPE_STRING:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise doc.error(path, f"expected text, got {value!r}")
        value = str(value)
    elif vtype.is_a(GObject.TYPE_ENUM):
        value = _enum_value(doc, path, pspec, value)
    elif vtype.is_a(GObject.TYPE_FLAGS):
        value = _flags_value(doc, path, pspec, value)
    elif vtype == Gst.Caps.__gtype__:
        value = _caps_value(doc, path, value)
    else:
        _set_as_text(doc, path, element, pspec, value)
        return
    # dcuscope's own elements: a text (or number) property that takes only some values.
    known = getattr(type(element), "CHOICES", {}).get(name)
    if known is not None and value not in known:
        raise doc.error(path, _one_of(known, value))
    element.set_property(name, value)


def _enum_value(doc: Document, path: KeyPath, pspec: GObject.ParamSpec, value: Any) -> int:
    members = type(pspec.default_value).__enum_values__.values()
    nicks = {m.value_nick: int(m) for m in members}
    names = {m.value_name: int(m) for m in members}
    if isinstance(value, str) and (value in nicks or value in names):
        return nicks.get(value, names.get(value))
    if isinstance(value, int) and not isinstance(value, bool) and value in nicks.values():
        return value
    raise doc.error(path, _one_of(nicks, value))


def _flags_value(doc: Document, path: KeyPath, pspec: GObject.ParamSpec, value: Any) -> int:
    """Flags as gst-launch takes them (``a+b``, ``a|b``, a number), or a YAML list of names."""
    members = [m for m in type(pspec.default_value).__flags_values__.values() if int(m)]
    by_name = {n: int(m) for m in members for n in (*m.value_nicks, *m.value_names)}
    every = 0
    for bits in by_name.values():
        every |= bits
    known = f"flags from: {', '.join(m.first_value_nick for m in members)} (joined with +)"
    if isinstance(value, int) and not isinstance(value, bool):
        if value < 0 or value & ~every:
            raise doc.error(path, f"{value} sets unknown bits: expected {known}")
        return value
    if isinstance(value, str):
        value = [part.strip() for part in value.replace("|", "+").split("+")] if value.strip() else []
    if not isinstance(value, list) or not all(isinstance(part, str) for part in value):
        raise doc.error(path, f"expected {known}; got {value!r}")
    result = 0
    for part in value:
        if part not in by_name:
            raise doc.error(path, f"unknown flag {part!r}: expected {known}")
        result |= by_name[part]
    return result


def _caps_value(doc: Document, path: KeyPath, value: Any) -> Gst.Caps:
    caps = Gst.Caps.from_string(value) if isinstance(value, str) else None
    if caps is None:
        raise doc.error(path, f"expected caps as gst-launch-1.0 writes them (video/x-raw,format=RGB,width=640); got {value!r}")
    for i in range(caps.get_size()):
        s = caps[i]
        if s.get_name() != "video/x-raw" or not s.has_field("format"):
            continue
        formats = s.get_value("format")
        for fmt in formats.array if isinstance(formats, Gst.ValueList) else [formats]:
            if not isinstance(fmt, str) or GstVideo.VideoFormat.from_string(fmt) == GstVideo.VideoFormat.UNKNOWN:
                raise doc.error(path, f"unknown video format {fmt!r} (known: {', '.join(_video_formats())})")
    return caps


@cache
def _video_formats() -> tuple[str, ...]:
    skip = (GstVideo.VideoFormat.UNKNOWN, GstVideo.VideoFormat.ENCODED)
    return tuple(GstVideo.video_format_to_string(f) for f in GstVideo.VideoFormat.__enum_values__.values() if f not in skip)


def _set_as_text(doc: Document, path: KeyPath, element: Gst.Element, pspec: GObject.ParamSpec, value: Any) -> None:
    """Fractions and other boxed types: the same parser gst-launch uses."""
    name = pspec.name
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise doc.error(path, f"expected a value as gst-launch-1.0 would take it, got {value!r}")
    before = element.get_property(name) if pspec.flags & GObject.ParamFlags.READABLE else None
    Gst.util_set_object_arg(element, name, str(value))
    if pspec.flags & GObject.ParamFlags.READABLE and element.get_property(name) == before and str(value) != str(before):
        raise doc.error(path, f"value {value!r} was not accepted for {name}")
