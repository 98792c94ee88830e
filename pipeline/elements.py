"""Stages -> GStreamer elements: factory lookup and property checking against the real pspecs.

Every installed element can be a stage; properties are checked by their GObject type and
range before anything runs, so a typo fails at load time with file:line, not mid-stream.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dcuscope.core.gst import GObject, Gst
from dcuscope.pipeline.config import PipelineConfig, StageConfig
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


def _check_and_set(doc, path, element: Gst.Element, pspec: GObject.ParamSpec, value: Any) -> None:
    vtype = pspec.value_type
    name = pspec.name
    if vtype == GObject.TYPE_BOOLEAN:
        if not isinstance(value, bool):
            raise doc.error(path, f"expected true or false, got {value!r}")
        element.set_property(name, value)
    elif vtype in _INT_TYPES or vtype in _FLOAT_TYPES:
        is_int = vtype in _INT_TYPES
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (is_int and not isinstance(value, int)):
            raise doc.error(path, f"expected {'an integer' if is_int else 'a number'}, got {value!r}")
        lo, hi = getattr(pspec, "minimum", None), getattr(pspec, "maximum", None)
        if lo is not None and hi is not None and not lo <= value <= hi:
            raise doc.error(path, f"{value} is out of range [{lo}, {hi}]")
        element.set_property(name, value)
    elif vtype == GObject.TYPE_STRING:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise doc.error(path, f"expected text, got {value!r}")
        element.set_property(name, str(value))
    elif vtype.is_a(GObject.TYPE_ENUM):
        members = type(pspec.default_value).__enum_values__.values()
        nicks = {m.value_nick: int(m) for m in members}
        names = {m.value_name: int(m) for m in members}
        if isinstance(value, str) and (value in nicks or value in names):
            element.set_property(name, nicks.get(value, names.get(value)))
        elif isinstance(value, int) and not isinstance(value, bool) and value in nicks.values():
            element.set_property(name, value)
        else:
            raise doc.error(path, f"expected one of: {', '.join(nicks)}; got {value!r}")
    else:
        # Caps, fractions, flags and other boxed types: the same parser gst-launch uses.
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise doc.error(path, f"expected a value as gst-launch-1.0 would take it, got {value!r}")
        before = element.get_property(name) if pspec.flags & GObject.ParamFlags.READABLE else None
        Gst.util_set_object_arg(element, name, str(value))
        if pspec.flags & GObject.ParamFlags.READABLE and element.get_property(name) == before and str(value) != str(before):
            raise doc.error(path, f"value {value!r} was not accepted for {name}")
