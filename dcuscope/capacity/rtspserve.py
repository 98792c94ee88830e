"""``--rtsp``: the config's file sources served as live RTSP streams on loopback, as cameras
would send them, by ``dcuscope serve-rtsp`` in its own process (it decodes and re-encodes every
stream on this machine: its CPU is reported beside the pipeline's)."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

READY_S = 30.0
BITRATE = 4000
"""kbit/s of the served streams (H.264)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RtspServer:
    """``dcuscope serve-rtsp CLIPS`` for the duration of a ``with`` block; ``uris`` are its mounts."""

    def __init__(self, clips: list[Path], bitrate: int = BITRATE):
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
        # Unbuffered stdout: select() sees every announced line.
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dcuscope.cli", "serve-rtsp", *map(str, self.clips), "--port", str(self.port),
             "--bitrate", str(self.bitrate)],
            stdout=subprocess.PIPE, stderr=self._errors, bufsize=0, start_new_session=True)
        self._started = time.monotonic()
        deadline = time.monotonic() + READY_S
        announced = b""
        try:
            while announced.count(b"rtsp://") < len(self.clips):  # one line per mount once it listens
                ready, _, _ = select.select([self.proc.stdout], [], [], max(deadline - time.monotonic(), 0))
                chunk = os.read(self.proc.stdout.fileno(), 4096) if ready else b""
                if not chunk:
                    self._errors.seek(0)
                    raise RuntimeError(f"serve-rtsp did not start within {READY_S:.0f} s: "
                                       f"{self._errors.read()[-500:].decode(errors='replace')}")
                announced += chunk
        except BaseException:
            self.__exit__()
            raise
        return self

    def cpu_cores(self) -> float | None:
        """CPU cores used since it started: utime + stime, fields 14 and 15 of /proc/PID/stat."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            cpu_s = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError, AttributeError):
            return None
        return cpu_s / max(time.monotonic() - self._started, 1e-3)

    def __exit__(self, *_exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.cores = self.cpu_cores()
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if self.proc is not None:
            self.proc.stdout.close()
        self._errors.close()
