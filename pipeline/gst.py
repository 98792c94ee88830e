"""The one place where GObject-introspection versions are pinned and GStreamer is initialised.

Every other module imports ``Gst``, ``GstBase``, ``GstVideo``, ``GObject`` and ``GLib`` from
here, so that ``gi.require_version`` is called exactly once and before any ``from
gi.repository import``.
"""

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstBase", "1.0")
gi.require_version("GstVideo", "1.0")

from gi.repository import GLib, GObject, Gst, GstBase, GstVideo  # noqa: E402

if not Gst.is_initialized():
    Gst.init(None)

__all__ = ["GLib", "GObject", "Gst", "GstBase", "GstVideo"]
