"""A real Redis server for the tests: Debian's ``redis-server``, in a temporary folder, on loopback.

Started without persistence (no RDB snapshots, no AOF): the relays keep nothing in Redis that must
outlive it (it carries their live pushes; the store keeps the data). ``stop()`` then ``start()``
again on the same port is a Redis restart as an operator's would be. ``RedisServer(tls=ISSUED)`` (a
server certificate of tests/tlscerts.py) takes TLS connections only (``--tls-port``, ``--port 0``),
without asking clients for certificates; its URL is ``rediss://``. ``RedisServer(replica_of=OTHER)``
is OTHER's replica; :class:`RedisSentinel` watches a master and promotes a replica when it dies.
"""

from __future__ import annotations

import shutil
import socket
import ssl
import subprocess
import tempfile
import time
from pathlib import Path

from tests.ports import free_port


def redis_binary() -> str:
    path = shutil.which("redis-server") or ("/usr/bin/redis-server" if Path("/usr/bin/redis-server").exists() else None)
    if path is None:
        raise RuntimeError("Redis is not installed (Debian's redis-server package): run `make setup`")
    return path


class RedisServer:
    def __init__(self, port: int | None = None, tls=None, replica_of: "RedisServer | None" = None) -> None:
        self.port = port or free_port()
        self.tls = tls
        self.more = ["--replicaof", "127.0.0.1", str(replica_of.port)] if replica_of is not None else []
        self.dir = Path(tempfile.mkdtemp(prefix="dcuscope-redis-"))
        self.log = self.dir / "redis.log"
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"{'rediss' if self.tls else 'redis'}://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 20.0) -> "RedisServer":
        port = ["--port", str(self.port)]
        if self.tls is not None:
            port = ["--port", "0", "--tls-port", str(self.port), "--tls-cert-file", str(self.tls.cert),
                    "--tls-key-file", str(self.tls.key), "--tls-auth-clients", "no"]
        self.proc = subprocess.Popen(
            [redis_binary(), *port, "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.dir), "--logfile", str(self.log), "--daemonize", "no", "--protected-mode", "yes",
             *self.more],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return self._answering("redis-server", timeout)

    def _answering(self, what: str, timeout: float):
        """This server once it answers PING; RuntimeError with its log's end if it exits or stays silent."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"{what} exited ({self.proc.returncode}): {self._log_tail()}")
            if self.ping():
                return self
            time.sleep(0.05)
        raise RuntimeError(f"{what} did not answer on 127.0.0.1:{self.port} in {timeout:g} s: {self._log_tail()}")

    def ping(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as raw:
                s = self._unchecked_tls().wrap_socket(raw) if self.tls else raw
                s.sendall(b"PING\r\n")
                return s.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    @staticmethod
    def _unchecked_tls() -> ssl.SSLContext:
        """TLS for the readiness check only: whether it answers, not whom."""
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
        return context

    def kill9(self) -> None:
        """Killed as a machine dies (SIGKILL)."""
        self.proc.kill()
        self.proc.wait(10)
        self.proc = None

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.dir, ignore_errors=True)

    def _log_tail(self) -> str:
        return self.log.read_text()[-1500:] if self.log.exists() else ""


class RedisSentinel(RedisServer):
    """One Redis Sentinel (``redis-server --sentinel``) watching ``master`` as service :data:`SERVICE`:
    a master silent for ``down_ms`` is replaced by one of its replicas (one sentinel is a quorum here)."""

    SERVICE = "dcuscope"

    def __init__(self, master: RedisServer, down_ms: int = 1000) -> None:
        super().__init__()
        self.master, self.down_ms = master, down_ms

    @property
    def url(self) -> str:
        """What a relay's ``--redis`` takes: the sentinels, the database, the service."""
        return f"redis+sentinel://127.0.0.1:{self.port}/0/{self.SERVICE}"

    def start(self, timeout: float = 20.0) -> "RedisSentinel":
        # Sentinel rewrites its configuration file (what it learns of replicas and failovers).
        config = self.dir / "sentinel.conf"
        config.write_text(f"port {self.port}\nbind 127.0.0.1\ndir {self.dir}\nlogfile {self.log}\n"
                          f"sentinel monitor {self.SERVICE} 127.0.0.1 {self.master.port} 1\n"
                          f"sentinel down-after-milliseconds {self.SERVICE} {self.down_ms}\n"
                          f"sentinel failover-timeout {self.SERVICE} 5000\n")
        self.proc = subprocess.Popen([redis_binary(), str(config), "--sentinel"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        return self._answering("redis sentinel", timeout)
