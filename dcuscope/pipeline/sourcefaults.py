"""What a person reads when a source fails or warns: GStreamer's message, its detail, and for
RTSP what to check.

GStreamer's own text for a refused RTSP connection is "Could not open resource for reading and
writing." with the cause ("Failed to connect.") only in the debug string, after the C function's
location; the last line of that string is the part worth showing.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from dcuscope.core.gst import GLib, Gst

RTSP_SCHEMES = ("rtsp://", "rtsps://", "rtspt://", "rtspu://")
RTSP_DEFAULT_PORT = 554


def describe_fault(error: GLib.Error, debug: str | None, location: str) -> str:
    """``error`` (from an ERROR or WARNING message of a source's element) in words, with the
    detail GStreamer keeps in ``debug`` and, for an RTSP source, what to check."""
    text = error.message.rstrip(".")
    lines = debug.strip().splitlines() if debug else []
    detail = lines[-1].strip().rstrip(".") if len(lines) > 1 else ""  # a single line is only the location
    if detail and detail not in text:
        text += f" ({detail})"
    if location.startswith(RTSP_SCHEMES):
        hint = rtsp_hint(error, location)
        if hint:
            text += f": {hint}"
    return text


def rtsp_hint(error: GLib.Error, location: str) -> str | None:
    """What to check when rtspsrc cannot reach the stream at ``location``; None when it is no such case."""
    url = urlsplit(location)
    try:
        port = url.port or RTSP_DEFAULT_PORT
    except ValueError:  # a port that is no number: the URI itself is the problem
        return None
    where = f"{url.hostname}:{port}"
    path = url.path or "/"
    if error.matches(Gst.ResourceError.quark(), Gst.ResourceError.OPEN_READ_WRITE):
        return (f"check that an RTSP server is running at {where}, that it serves the path {path}, "
                f"and that no firewall blocks port {port}")
    if error.matches(Gst.ResourceError.quark(), Gst.ResourceError.NOT_FOUND):
        return f"the server at {where} has no stream at {path}: check the path"
    return None
