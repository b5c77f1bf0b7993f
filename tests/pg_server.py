"""A real PostgreSQL server for the tests, started by them: Debian's `postgresql` binaries, a
temporary data folder, a free loopback port, trust authentication for a user `cell`.

initdb and postgres refuse to run as root (CI runs as root), so as root they run as the
`postgres` system user (or `nobody`). `why_no_postgresql()` says why the tests must skip
where the server cannot be had (`.ci/run` installs it where it is missing).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from tests.ports import free_port


def bin_dir() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/postgres"), key=lambda p: int(p.split("/")[4]))
    return Path(found[-1]).parent if found else None


def _run_as() -> pwd.struct_passwd | None:
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            return pwd.getpwnam(name)
        except KeyError:
            continue
    return None


def why_no_postgresql() -> str | None:
    if bin_dir() is None:
        return "PostgreSQL is not installed (Debian package `postgresql`; .ci/run installs it)"
    if os.geteuid() == 0 and _run_as() is None:
        return "running as root with no `postgres` or `nobody` user to run PostgreSQL as"
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "psycopg is not installed (pip install 'psycopg[binary]')"
    return None


class PostgresServer:
    def __init__(self) -> None:
        found = bin_dir()
        if found is None:
            raise RuntimeError(str(why_no_postgresql()))
        self.bin: Path = found
        self.user = _run_as()
        self.root = Path(tempfile.mkdtemp(prefix="cell-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        if self.user is not None:
            os.chown(self.root, self.user.pw_uid, self.user.pw_gid)
        self._call([str(self.bin / "initdb"), "-D", str(self.data), "-U", "cell", "--auth=trust", "-E", "UTF8"])

    @property
    def url(self) -> str:
        return f"postgresql://cell@127.0.0.1:{self.port}/postgres"

    def _kw(self) -> dict:
        if self.user is None:
            return {}
        return {"user": self.user.pw_uid, "group": self.user.pw_gid, "extra_groups": []}

    def _call(self, cmd: list[str]) -> None:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=self.root, **self._kw())
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {r.stderr.strip()[-500:]}")

    def start(self, timeout_s: float = 60.0) -> None:
        cmd = [
            str(self.bin / "postgres"),
            "-D",
            str(self.data),
            "-p",
            str(self.port),
            "-k",
            str(self.root),
            "-c",
            "listen_addresses=127.0.0.1",
            "-c",
            "fsync=off",
            "-c",
            "shared_buffers=16MB",
        ]
        log = open(self.root / "server.log", "ab")  # noqa: SIM115 - the server's, closed with it
        self.proc = subprocess.Popen(cmd, stdout=log, stderr=log, cwd=self.root, **self._kw())
        log.close()
        import psycopg

        deadline = time.monotonic() + timeout_s
        while True:
            try:
                psycopg.connect(self.url, connect_timeout=2).close()
                return
            except psycopg.OperationalError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    tail = (self.root / "server.log").read_text(errors="replace")[-800:]
                    raise RuntimeError(f"PostgreSQL did not start on port {self.port}: {tail}") from None
                time.sleep(0.1)

    def stop(self) -> None:
        """Fast shutdown (SIGINT): clients are cut off, as when the server goes away."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)
