"""`run-cell serve --dry-run` in a subprocess on free ports, for the browser tests and the
screen benchmark: started in a folder of its own, its screen's address read from the ready line,
stopped with SIGTERM (the safe stop) and killed only if it does not end."""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
import threading
from pathlib import Path

from tests.ports import free_port

READY = re.compile(r"^ready: .*screen (https?://\S+?/)")


class ServeProcess:
    def __init__(
        self,
        workdir: Path,
        *extra: str,
        timeout_s: float = 60.0,
        nofile: int | None = None,
        dry_run: bool = True,
    ):
        """`nofile`: the process's RLIMIT_NOFILE, soft and hard (`ulimit -n`). `dry_run=False`: a production
        serve (its history is production's: data/history.sqlite or history.url) over the config's devices,
        the simulated world's camera and arm unless the config names others."""
        self.workdir = workdir
        cmd = [
            sys.executable,
            "-m",
            "cell.cli",
            "serve",
            *(["--dry-run"] if dry_run else []),
            "--opcua-port",
            str(free_port()),
            "--http-port",
            str(free_port()),
            *extra,
        ]
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
        self.opcua_port = int(cmd[cmd.index("--opcua-port") + 1])

        def limit() -> None:
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.proc = subprocess.Popen(
            cmd,
            cwd=workdir,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
            preexec_fn=limit if nofile is not None else None,
        )
        self.lines: list[str] = []
        self.url = self._wait_ready(timeout_s)
        self._drain = threading.Thread(target=self._read_rest, daemon=True)
        self._drain.start()

    def _wait_ready(self, timeout_s: float) -> str:
        timer = threading.Timer(timeout_s, self.proc.kill)
        timer.start()
        assert self.proc.stdout is not None  # stdout=PIPE
        try:
            for line in self.proc.stdout:
                self.lines.append(line.rstrip())
                if m := READY.match(line):
                    return m.group(1)
        finally:
            timer.cancel()
        self.proc.wait(timeout=10)
        raise RuntimeError(
            f"run-cell serve ended (exit {self.proc.returncode}) before its ready line:\n" + "\n".join(self.lines[-20:])
        )

    def _read_rest(self) -> None:
        assert self.proc.stdout is not None  # stdout=PIPE
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())

    def stop(self, timeout_s: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._drain.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode
