"""The one place where GObject-introspection versions are pinned and GStreamer is initialised.

Every other module imports ``Gst``, ``GstBase``, ``GstVideo``, ``GObject`` and ``GLib`` from
here, so that ``gi.require_version`` is called exactly once and before any ``from
gi.repository import``.
"""

import ctypes
import os

# GStreamer links libunwind, which exports the C++ unwinding ABI (_Unwind_*). Once it is global,
# a C++ exception inside onnxruntime or OpenCV unwinds through a mix of libunwind and libgcc_s
# and aborts the process. Loading libgcc_s globally first keeps the unwinder consistent.
ctypes.CDLL("libgcc_s.so.1", mode=os.RTLD_GLOBAL)

import gi  # noqa: E402

from dcuscope.core.errors import DcuscopeError  # noqa: E402

gi.require_version("Gst", "1.0")
gi.require_version("GstBase", "1.0")
gi.require_version("GstVideo", "1.0")
gi.require_version("GstPbutils", "1.0")
gi.require_version("GstApp", "1.0")
RTSP_SERVER_PACKAGE = "gir1.2-gst-rtsp-server-1.0"
"""GstRtspServer's bindings, as Debian and Ubuntu name them: only the rtsp sink and serve-rtsp need them."""
try:
    gi.require_version("GstRtspServer", "1.0")
except ValueError:
    pass  # rtsp_server() says what to install when it is needed

from gi.repository import GLib, GObject, Gst, GstBase, GstVideo  # noqa: E402

if not Gst.is_initialized():
    Gst.init(None)




def _quiet_floating_warning(domain: str, level, message: str, *_user) -> None:
    # PyGObject < 3.44 sinks the floating reference of elements written in Python, and
    # gst_element_factory_create complains on every such element. Harmless; hide only that.
    if "should be floating" not in message:
        GLib.log_default_handler(domain, level, message, None)


GLib.log_set_handler("GStreamer", GLib.LogLevelFlags.LEVEL_CRITICAL, _quiet_floating_warning, None)


def rtsp_server():
    """GStreamer's RTSP server bindings (``GstRtspServer``); DcuscopeError naming the package if missing."""
    try:
        from gi.repository import GstRtspServer
    except ImportError as exc:
        raise DcuscopeError(f"serving RTSP needs GStreamer's RTSP server bindings: apt-get install {RTSP_SERVER_PACKAGE}") from exc
    return GstRtspServer


__all__ = ["GLib", "GObject", "Gst", "GstBase", "GstVideo", "rtsp_server"]
