"""A real PostgreSQL server for the tests: Debian's PostgreSQL 15, in a temporary folder, on loopback.

PostgreSQL refuses to run as root: as root the server is made and run as Debian's ``postgres``
user (``runuser``), in a folder given to it; as anyone else, as oneself. Each pytest worker starts
one server (the ``postgres`` fixture of tests/conftest.py), each test gets a database of its own
(``pg_url``). Durability settings are off (fsync, synchronous commit, full-page writes): the tests
check what the relay commits and reads back, not the disk; a server killed mid-test loses nothing the
tests read. ``PostgresServer(durable=True)`` keeps PostgreSQL's defaults for them instead (all on: a
commit returns once its WAL is on disk), as users run it: the benchmarks time the relay on that.
``PostgresServer(listen=[ADDR])`` also listens on ADDR (the host's end of a test's network namespace,
tests/relay/nsnet.py), trusting clients from the subnets the host is directly connected to.
``PostgresServer(tls=ISSUED)`` (a server certificate of tests/tlscerts.py) takes TLS connections only
(``ssl=on``, pg_hba's ``hostssl``; plain TCP is refused): user ``postgres`` without a password, and user
``USER`` (:data:`USER`) with password :data:`PASSWORD` (scram-sha-256), as a relay would log in.
``PostgresServer(synchronous=True)`` is a primary whose commits wait for its synchronous standby
(``synchronous_commit = on``, the standby named :data:`STANDBY`), made by :meth:`PostgresServer.standby`
(``pg_basebackup -R``): :meth:`PostgresServer.kill9` kills a server as a machine dies,
:meth:`PostgresServer.promote` makes a standby the primary. Those two settings are in the primary's
``postgresql.conf``, as docs/store-failover.md sets them up, not on its command line: ``pg_basebackup``
copies them to the standby, which, promoted, keeps waiting for a standby named so (itself), as a
promoted standby does, until they are changed (docs/store-failover.md, the promotion by hand).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
import uuid
from pathlib import Path
from typing import Sequence
from urllib.parse import quote

from tests.ports import free_port

SETTINGS = "-c max_connections=300 -c shared_buffers=64MB"
NO_DISK = "-c fsync=off -c full_page_writes=off"
FAST = f"{NO_DISK} -c synchronous_commit=off"
"""The tests' durability settings: nothing waits for the disk."""
DURABLE = "-c fsync=on -c synchronous_commit=on -c full_page_writes=on"
"""PostgreSQL's defaults, said explicitly: every commit waits for its WAL to reach the disk."""
STANDBY = "dcuscope_standby"
"""The standby's name (its ``cluster_name``), which its WAL receiver gives the primary (libpq's application_name)."""
SYNCHRONOUS = f"synchronous_commit = on\nsynchronous_standby_names = '{STANDBY}'\n"
"""A primary's commits wait for its standby (by name), in its postgresql.conf: the tests' FAST settings
but for that (a ``synchronous_commit=off`` on the command line would override the file)."""
USER = "dcuscope"
PASSWORD = "s3cret pw/ok"
"""A TLS server's password user: its password has characters a URL must escape."""
TLS_HBA = ("local all all trust\nhostssl all postgres 127.0.0.1/32 trust\n"
           f"hostssl all {USER} 127.0.0.1/32 scram-sha-256\nhostnossl all all all reject\n")


def bindir() -> Path:
    """The newest installed PostgreSQL's programs (Debian keeps them out of PATH)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if not found:
        raise RuntimeError("PostgreSQL is not installed (Debian's postgresql package): run `make setup`")
    return Path(found[-1]).parent


class PostgresServer:
    def __init__(self, durable: bool = False, listen: Sequence[str] = (), tls=None, synchronous: bool = False) -> None:
        """``durable``: fsync, synchronous_commit and full_page_writes on (PostgreSQL's defaults), not
        off as the tests run it. ``listen``: addresses to listen on besides 127.0.0.1 (they must exist
        when the server starts); clients reaching them from a directly connected subnet (pg_hba's
        ``samenet``: a namespace's end of its veth pair) are trusted, as on loopback. ``tls``: the
        server's certificate and key (tests/tlscerts.py ``Issued``): TLS connections only. ``synchronous``:
        commits wait for the standby :meth:`standby` makes (:data:`SYNCHRONOUS`, in its postgresql.conf)."""
        self.durable = durable
        self.tls = tls
        self.synchronous = synchronous
        self.listen = ["127.0.0.1", *listen]
        self.settings = (f"-c listen_addresses={','.join(self.listen)} {SETTINGS} "
                         f"{DURABLE if durable else NO_DISK if synchronous else FAST}")
        self.bin = bindir()
        self.port = free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="dcuscope-pg-"))
        self.data = self.dir / "data"
        self.log = self.dir / "server.log"
        self.as_root = os.geteuid() == 0
        if self.as_root:
            user = pwd.getpwnam("postgres")
            os.chown(self.dir, user.pw_uid, user.pw_gid)
        if tls is not None:
            # PostgreSQL reads a key owned by its user, mode 0600, and no one else's.
            for name, source in (("server.crt", tls.cert), ("server.key", tls.key)):
                shutil.copyfile(source, self.dir / name)
                os.chmod(self.dir / name, 0o600)
                if self.as_root:
                    os.chown(self.dir / name, user.pw_uid, user.pw_gid)
            self.settings += f" -c ssl=on -c ssl_cert_file={self.dir / 'server.crt'} -c ssl_key_file={self.dir / 'server.key'}"

    def _run(self, *args: str, timeout: float = 60) -> str:
        cmd = [str(self.bin / args[0]), *args[1:]]
        if self.as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=self.dir)
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(args[:2])} failed ({done.returncode}): {done.stderr[-2000:]}\n{log}")
        return done.stdout

    def start(self) -> "PostgresServer":
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--no-sync")
        if self.synchronous:
            with open(self.data / "postgresql.conf", "a") as conf:
                conf.write(SYNCHRONOUS)
        if len(self.listen) > 1:
            with open(self.data / "pg_hba.conf", "a") as hba:
                hba.write("host all all samenet trust\n")
        if self.tls is not None:
            (self.data / "pg_hba.conf").write_text(TLS_HBA)
        self.resume()
        if self.tls is not None:
            import psycopg

            with psycopg.connect(self.url(), autocommit=True) as conn:
                conn.execute(f"CREATE ROLE {USER} LOGIN PASSWORD '{PASSWORD}'")
        return self

    def resume(self) -> "PostgresServer":
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                  "-o", f"-p {self.port} -k {self.dir} {self.settings}", "start")
        return self

    def standby(self, name: str = STANDBY) -> "PostgresServer":
        """A standby of this server named ``name`` (its ``cluster_name``), streaming its WAL
        (``pg_basebackup -R``), started on its own port; this server's synchronous standby if it is
        ``synchronous`` and ``name`` is :data:`STANDBY`. It has this server's configuration files (the
        data directory's, copied): promoted, it waits for the standby they name, until told otherwise."""
        other = PostgresServer(durable=self.durable, synchronous=self.synchronous)
        other.settings += f" -c cluster_name={name}"
        try:
            # A checkpoint at once, not a spread one: after a promotion, or with much written, that one
            # takes minutes (checkpoint_completion_target of checkpoint_timeout).
            other._run("pg_basebackup", "-D", str(other.data), "-R", "-X", "stream", "--checkpoint=fast", "--no-sync",
                       "-h", "127.0.0.1", "-p", str(self.port), "-U", "postgres", timeout=120)
            return other.resume()
        except BaseException:
            other.close()
            raise

    def promote(self) -> None:
        """A standby becomes a primary (``pg_ctl promote``, waiting until it takes writes)."""
        self._run("pg_ctl", "-D", str(self.data), "-w", "-t", "60", "promote")

    def kill9(self) -> None:
        """The server killed as a machine dies: SIGKILL to the postmaster and to every process it started
        (the postmaster stopped first, so that it starts none meanwhile). Returns once they are gone;
        their lock file is left as a dead machine leaves it, naming no live process."""
        pid = int((self.data / "postmaster.pid").read_text().split()[0])
        os.kill(pid, signal.SIGSTOP)
        victims = [pid, *(int(Path(stat).parent.name) for stat in glob.glob("/proc/[0-9]*/stat")
                          if _stat(stat)[1:2] == [str(pid)])]
        for victim in victims:
            try:
                os.kill(victim, signal.SIGKILL)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 30
        while any(_stat(f"/proc/{v}/stat")[:1] not in ([], ["Z"]) for v in victims):
            if time.monotonic() > deadline:
                raise RuntimeError(f"PostgreSQL processes {victims} outlived SIGKILL")
            time.sleep(0.02)
        # A zombie (its parent, here, may be slow to reap it) still holds its PID: PostgreSQL would take
        # the lock files for a live server's.
        (self.data / "postmaster.pid").unlink(missing_ok=True)
        (self.dir / f".s.PGSQL.{self.port}.lock").unlink(missing_ok=True)

    def stop(self, mode: str = "fast") -> None:
        """``fast`` ends every connection and stops; ``immediate`` as if the server crashed."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "stop")

    def url(self, database: str = "postgres", host: str = "127.0.0.1") -> str:
        """The URL of ``database`` through ``host`` (one of the addresses listened on); a TLS server's
        over TLS, its certificate unchecked (the tests' own connections)."""
        return f"postgresql://postgres@{host}:{self.port}/{database}" + ("?sslmode=require" if self.tls else "")

    def user_url(self, database: str, ca, host: str = "127.0.0.1") -> str:
        """A TLS server's URL of ``database`` as user :data:`USER` with its password, the server's
        certificate checked against ``ca`` (a file) and ``host`` (``sslmode=verify-full``)."""
        return (f"postgresql://{USER}:{quote(PASSWORD, safe='')}@{host}:{self.port}/{database}"
                f"?sslmode=verify-full&sslrootcert={quote(str(ca))}")

    def new_database(self, host: str = "127.0.0.1") -> str:
        """A fresh empty database; its URL through ``host``."""
        import psycopg

        name = "t_" + uuid.uuid4().hex[:12]
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}" + (f" OWNER {USER}" if self.tls else ""))
        return self.url(name, host)

    def close(self) -> None:
        try:
            self.stop("immediate")
        except (RuntimeError, subprocess.TimeoutExpired):
            pass
        shutil.rmtree(self.dir, ignore_errors=True)


def _stat(path: str) -> list[str]:
    """A process's state and parent PID (``/proc/PID/stat``'s fields 3 and 4), or [] if it is gone."""
    try:
        return Path(path).read_text().rsplit(")", 1)[1].split()[:2]
    except (OSError, IndexError):
        return []
