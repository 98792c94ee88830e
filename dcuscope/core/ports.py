"""The TCP port a server command (relay, demo, serve-rtsp) listens on, checked before it starts
anything: a taken port is a bad argument (exit 2, one line naming ``--port``), not a failure
from inside a server that is half up."""

from __future__ import annotations

import socket

from dcuscope.core.errors import UsageError


def check_port_free(host: str, port: int, hint: str = "pick a free one with --port", option: str | None = "--port") -> None:
    """UsageError when nothing could listen on ``host:port`` now; port 0 (any free one) passes.
    The message starts with ``option PORT: `` (None: a caller that names the key itself)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        # as the servers bind: only a listener is in the way, not connections in TIME_WAIT
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            said = f"{option} {port}: " if option else ""
            raise UsageError(f"{said}cannot listen on {host}:{port} ({exc.strerror or exc}): {hint}") from None
