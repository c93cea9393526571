"""A real PostgreSQL server for the tests and the load benchmark, started in a temporary directory and
stopped after (``python3 scripts/pg_server.py`` runs one until interrupted and prints its URL).

Debian's server binaries (``initdb``, ``pg_ctl``; ``python3 dev.py test`` installs the package when
missing).  PostgreSQL refuses to run as root: when the tests do, the server runs as the ``postgres``
system user (``runuser``) in a directory it owns.  It listens on 127.0.0.1 at a free port with trust
authentication; fsync is off (a test server: durability across an OS crash is not what is tested).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _binary(name: str) -> str:
    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"),
                                                   reverse=True)), None)
    if found is None:
        raise RuntimeError(f"PostgreSQL's {name} is not installed: run python3 dev.py test (it installs "
                           "Debian's postgresql), or apt-get install postgresql")
    return found


def _alive(pid: int) -> bool:
    """Whether the process runs (a zombie, killed but not reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


class PostgresServer:
    """``PostgresServer()`` starts a cluster; ``dsn`` to connect; ``stop()`` removes it."""

    def __init__(self):
        self.port = free_port()
        self.root = Path(tempfile.mkdtemp(prefix="yauyau-pg-"))
        self.data = self.root / "data"
        self._as = []
        if os.geteuid() == 0:
            user = pwd.getpwnam("postgres")
            os.chown(self.root, user.pw_uid, user.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"]
        self._run(_binary("initdb"), "-D", str(self.data), "-A", "trust", "-U", "yauyau", "--no-sync",
                  "-E", "UTF8", "--locale", "C")
        self.start()
        self.dsn = f"postgresql://yauyau@127.0.0.1:{self.port}/postgres"

    def start(self) -> None:
        """Start the server (again, after :meth:`crash`: it recovers from its write-ahead log).  Commits
        are asynchronous by default here, as on a server tuned for throughput: a client that needs a
        commit durable asks for it (the session store does, per transaction)."""
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off "
                   "-c synchronous_commit=off -c full_page_writes=off -c max_connections=200")
        self._run(_binary("pg_ctl"), "-D", str(self.data), "-o", options, "-l", str(self.root / "log"),
                  "-w", "-t", "60", "start")

    def crash(self) -> None:
        """SIGKILL every process of the server at once, the WAL writer first (a power cut of the database
        host, as far as the server's memory is concerned): what it had not written is lost."""
        import signal

        postmaster = int((self.data / "postmaster.pid").read_text().split()[0])
        os.kill(postmaster, signal.SIGSTOP)  # it must not restart what dies first
        children = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == postmaster:
                children.append(int(stat.parent.name))
        for pid in [*children, postmaster]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(_alive(pid) for pid in [*children, postmaster]):
            time.sleep(0.05)
        # Where nothing reaps orphans (a container whose first process is not an init), the killed
        # postmaster stays a zombie, which a new postmaster takes for a live one ("lock file already
        # exists"); every process of this server is dead, so its lock files are stale.
        for stale in (self.data / "postmaster.pid", self.root / f".s.PGSQL.{self.port}.lock",
                      self.root / f".s.PGSQL.{self.port}"):
            stale.unlink(missing_ok=True)

    def _run(self, *command: str) -> None:
        done = subprocess.run([*self._as, *command], capture_output=True, text=True, cwd=self.root)
        if done.returncode != 0:
            log = (self.root / "log").read_text() if (self.root / "log").exists() else ""
            raise RuntimeError(f"{Path(command[0]).name} failed: {done.stderr[-2000:]}{log[-2000:]}")

    def database(self, name: str) -> str:
        """A fresh database on this server; its DSN."""
        import psycopg

        with psycopg.connect(self.dsn, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return f"postgresql://yauyau@127.0.0.1:{self.port}/{name}"

    def stop(self) -> None:
        try:
            if (self.data / "postmaster.pid").exists():  # not after a crash() with no start()
                self._run(_binary("pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            time.sleep(0.1)
            shutil.rmtree(self.root, ignore_errors=True)


if __name__ == "__main__":
    server = PostgresServer()
    print(server.dsn, flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
        sys.exit(0)
