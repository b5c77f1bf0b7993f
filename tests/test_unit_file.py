"""The line service started exactly as configs/pick-cell.service starts it (issue 33, item 1).

The unit file itself is parsed: ExecStart=, User=/Group=/SupplementaryGroups=, WorkingDirectory=,
StateDirectory=/CacheDirectory=/RuntimeDirectory=/ReadWritePaths=, ProtectSystem=strict,
ProtectHome=, PrivateTmp=, NoNewPrivileges=, Environment=, LimitNOFILE=. In a mount namespace
of its own (tests/unit_sandbox.py) every mount is read-only but the unit's writable folders,
the checkout lies read-only where ExecStart expects it, and `serve` runs as the unit's user
(or `nobody` where that user does not exist: home /nonexistent, nothing of its own). The
users file is made as the commissioning steps make it (`run-cell user add --owner`). A
production shift with history required then records picks, an engineer recalibrates from the
screen while it is paused (the calibration written, its picture drawn), and SIGTERM ends it
cleanly. The test tools (pyproject.toml's [test] extra) are hidden from the service: a
runtime-only install. Anything the service writes outside the unit's folders, or any module
of the test tools it imports, shows here as a failure.

Needs root (a mount namespace, a user switch); skips, saying why, without it.
"""

from __future__ import annotations

import contextlib
import grp
import json
import os
import pwd
import re
import shlex
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from importlib import metadata
from pathlib import Path

import httpx
import pytest
from packaging.requirements import Requirement

from tests.ports import free_port
from tests.unit_sandbox import environment, parse_unit, words

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "configs" / "pick-cell.service"
READY = re.compile(r"^ready: .*screen (https?://\S+?/)")
PASSWORD = "line-engineer-1"
PICKS = 3
# what systemd gives a service besides its own settings (systemd.exec(5), "Environment variables")
SYSTEMD_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
DIRECTORIES = {  # the unit's setting -> (its root, the variable systemd sets)
    "StateDirectory": ("/var/lib", "STATE_DIRECTORY"),
    "CacheDirectory": ("/var/cache", "CACHE_DIRECTORY"),
    "RuntimeDirectory": ("/run", "RUNTIME_DIRECTORY"),
    "LogsDirectory": ("/var/log", "LOGS_DIRECTORY"),
}
# a warning in the service's log that a write was refused: what this test is here to find
REFUSED_WRITE = re.compile(r"Read-only file system|Permission denied|not written|not kept|cannot write", re.I)


def why_no_sandbox() -> str | None:
    if os.geteuid() != 0:
        return "needs root: a mount namespace (unshare -m) and a switch to the unit's user, as systemd makes them"
    for tool in ("unshare", "setpriv", "mount"):
        if shutil.which(tool) is None:
            return f"needs {tool} (util-linux) to start the service as its unit does"
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"unshare -m is refused here (a container without CAP_SYS_ADMIN?): {probe.stderr.strip()}"
    return None


pytestmark = pytest.mark.timeout(120)
needs_root = pytest.mark.skipif(why_no_sandbox() is not None, reason=str(why_no_sandbox()))


def one(service: dict[str, list[str]], key: str, default: str | None = None) -> str:
    values = service.get(key) or ([] if default is None else [default])
    assert values, f"{UNIT.name}: [Service] {key}= is not set"
    return values[-1]


def yes(service: dict[str, list[str]], key: str) -> bool:
    return bool(service.get(key)) and one(service, key).lower() in ("yes", "true", "on", "1")


@contextlib.contextmanager
def mount_points(paths: list[Path]):
    """The folders the namespace mounts on, made where missing (as systemd makes StateDirectory=) and
    removed afterwards: empty, they change nothing outside the namespace."""
    made: list[Path] = []
    try:
        for path in paths:
            for missing in reversed([p for p in (path, *path.parents) if not p.exists()]):
                missing.mkdir()
                made.append(missing)
        yield
    finally:
        for path in reversed(made):
            with contextlib.suppress(OSError):
                path.rmdir()


def service_account(service: dict[str, list[str]]) -> tuple[pwd.struct_passwd, int, list[int]]:
    """The unit's user (or nobody where it does not exist here), its group, its supplementary groups."""
    try:
        user = pwd.getpwnam(one(service, "User"))
        gid = grp.getgrnam(one(service, "Group")).gr_gid if service.get("Group") else user.pw_gid
    except KeyError:
        user = pwd.getpwnam("nobody")
        gid = user.pw_gid
    groups = []
    for name in words(service.get("SupplementaryGroups", [])):
        with contextlib.suppress(KeyError):
            groups.append(grp.getgrnam(name).gr_gid)
    return user, gid, groups


def line_config(path: Path) -> None:
    """A production cell on the simulated world (its camera and arm stand in for the line's), with
    users (so HTTPS and OPC UA certificates are made), history required and its images kept."""
    path.write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
        "[sim]\nreference_marks_mm = []\nspeed_factor = 60\n"
        "[sim.feeder]\nparts_per_minute = 6\nmax_on_table = 25\n"
        f'[service]\nopcua_port = {free_port()}\nhttp_port = {free_port()}\ncapture_interval_s = 0.5\nusers_file = "users.json"\n'
        "[history]\nrequired = true\nimages = true\n"
    )


def _closure(requirements: list[Requirement]) -> set[str]:
    """The installed distributions these requirements pull in, each with its own requirements."""
    seen: set[str] = set()
    todo = list(requirements)
    while todo:
        req = todo.pop()
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        if name in seen:
            continue
        try:
            dist = metadata.distribution(req.name)
        except metadata.PackageNotFoundError:
            continue
        seen.add(name)
        for line in dist.requires or []:
            sub = Requirement(line)
            if sub.marker is None or any(sub.marker.evaluate({"extra": e}) for e in (req.extras or {""})):
                todo.append(sub)
    return seen


def tools_of_the_tests() -> list[Path]:
    """What the [test] extra installs that the cell's own dependencies do not (pytest, Playwright, mypy,
    ruff, httpx ... and theirs): the top-level modules and packages, to be hidden from the service."""
    requires = [Requirement(line) for line in metadata.distribution("pick-cell").requires or []]
    runtime = [r for r in requires if r.marker is None or r.marker.evaluate({"extra": ""})]
    tests = [r for r in requires if r not in runtime and r.marker is not None and r.marker.evaluate({"extra": "test"})]
    hidden = []
    for name in sorted(_closure(tests) - _closure(runtime)):
        dist = metadata.distribution(name)
        tops = {f.parts[0] for f in dist.files or [] if f.parts[0] not in ("..", "__pycache__")}
        for top in sorted(tops):
            path = Path(str(dist.locate_file(top)))
            if not top.endswith((".dist-info", ".pth")) and (path.is_dir() or path.suffix == ".py"):
                hidden.append(path)
    return hidden


def poisoned(modules: list[Path], folder: Path) -> list[tuple[str, str]]:
    """(a stand-in, the module it hides): importing it raises ImportError, as in an install without the extra."""
    folder.mkdir()
    package, module = folder / "package", folder / "module.py"
    package.mkdir()
    text = 'raise ImportError(f"{__name__}: a test tool, not in a runtime install (pyproject.toml [test] extra)")\n'
    (package / "__init__.py").write_text(text)
    module.write_text(text)
    return [(str(package if path.is_dir() else module), str(path)) for path in modules]


def run_cell(*args: str, cwd: Path, stdin: str = "") -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "cell.cli", *args], cwd=cwd, env=env, input=stdin, capture_output=True, text=True
    )


def picks(database: Path) -> int:
    if not database.exists():
        return 0
    with contextlib.closing(sqlite3.connect(f"file:{database}?mode=ro", uri=True)) as db:
        try:
            return db.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone()[0]
        except sqlite3.OperationalError:  # not made yet
            return 0


def wait_for(cond, timeout_s: float, what: str, output: list[str]) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}:\n" + "\n".join(output[-30:])
        time.sleep(0.1)


def test_the_units_config_and_working_folder_lie_in_the_folder_systemd_makes_for_it():
    """Without root too: the config ExecStart names and WorkingDirectory= (where line.toml's relative paths
    lead: calibration, logs, data, recipes, users) are in StateDirectory=; the cache has a folder of its own."""
    service = parse_unit(UNIT.read_text())["Service"]
    state = [Path("/var/lib", name) for name in words(service["StateDirectory"])]
    argv = shlex.split(one(service, "ExecStart"))
    for path in (Path(argv[argv.index("--config") + 1]), Path(one(service, "WorkingDirectory"))):
        assert any(path.is_relative_to(s) for s in state), (path, state)
    assert words(service["CacheDirectory"]) and one(service, "User") != "root"


def test_the_cache_is_systemds_cache_directory_under_the_unit(monkeypatch, tmp_path):
    from cell.cachedir import user_cache_dir

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("CACHE_DIRECTORY", raising=False)
    assert user_cache_dir("opcua") == tmp_path / "xdg" / "pick-cell" / "opcua"
    monkeypatch.setenv("CACHE_DIRECTORY", f"{tmp_path / 'systemd'}:{tmp_path / 'other'}")
    assert user_cache_dir("opcua") == tmp_path / "systemd" / "opcua"


@needs_root
def test_the_unit_file_starts_a_production_shift_that_records_and_stops_cleanly(tmp_path):
    unit = parse_unit(UNIT.read_text())
    service = unit["Service"]
    argv = shlex.split(one(service, "ExecStart"))
    user, gid, groups = service_account(service)
    uid = user.pw_uid
    assert one(service, "ProtectSystem") == "strict", (
        "the test expects the whole system read-only but the unit's folders"
    )

    # the unit's writable folders, each a folder of the test's owned by the service user
    writable: list[tuple[Path, Path]] = []
    env = {
        "PATH": SYSTEMD_PATH,
        "LANG": "C.UTF-8",
        "HOME": user.pw_dir,
        "USER": user.pw_name,
        "LOGNAME": user.pw_name,
        "SHELL": user.pw_shell,
    }
    for key, (base, variable) in DIRECTORIES.items():
        names = words(service.get(key, []))
        mode = int(one(service, f"{key}Mode", "0755"), 8)
        for name in names:
            source = tmp_path / key / name
            source.mkdir(parents=True)
            os.chown(source, uid, gid)
            source.chmod(mode)
            writable.append((source, Path(base, name)))
        if names:
            env[variable] = ":".join(str(Path(base, n)) for n in names)
    for n, path in enumerate(words(service.get("ReadWritePaths", []))):
        source = tmp_path / "ReadWritePaths" / str(n)
        source.mkdir(parents=True)
        os.chown(source, uid, gid)
        writable.append((source, Path(path.lstrip("-+"))))
    env.update(environment(service.get("Environment", [])))

    # the software: ExecStart's venv's folder holds the checkout, its .venv this test's interpreter's
    program = Path(argv[0])
    assert program.parent.name == "bin" and program.parent.parent.name == ".venv", (
        f"ExecStart runs {program}: the test lays the checkout where its .venv lies"
    )
    software = program.parent.parent.parent
    entries = {p.name: str(p) for p in ROOT.iterdir() if p.name not in (".venv", ".git")}
    entries[".venv"] = sys.prefix
    # the venv's own entry script runs the checkout's code (its editable install may point elsewhere)
    env["PYTHONPATH"] = str(software)

    # the config ExecStart names, in the unit's writable folders (the cell's folder)
    config = Path(argv[argv.index("--config") + 1])
    into = [(s, t) for s, t in writable if config.is_relative_to(t)]
    assert into, f"ExecStart's --config {config} lies in none of the unit's folders {[str(t) for _, t in writable]}"
    source, target = into[0]
    config_here = source / config.relative_to(target)
    line_config(config_here)
    cwd = Path(one(service, "WorkingDirectory"))
    cwd_here = next(s / cwd.relative_to(t) for s, t in writable if cwd.is_relative_to(t))
    state = cwd_here

    # the users file as the commissioning steps make it: as root, it must be given to the service user
    refused = run_cell(
        "user", "add", "eng1", "--role", "engineer", "--config", str(config_here), cwd=state, stdin=PASSWORD + "\n"
    )
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert f"--owner {user.pw_name}" in refused.stderr and not (state / "users.json").exists(), refused.stderr
    added = run_cell(
        "user", "add", "eng1", "--role", "engineer", "--owner", user.pw_name, "--config", str(config_here),
        cwd=state, stdin=PASSWORD + "\n",
    )  # fmt: skip
    assert added.returncode == 0, added.stdout + added.stderr
    users = (state / "users.json").stat()
    assert (users.st_uid, users.st_mode & 0o777) == (uid, 0o600)

    hide = []
    if yes(service, "ProtectHome"):  # the test's own software may live there: then it stays (read-only)
        needed = [Path(p).resolve() for p in (sys.prefix, sys.base_prefix, ROOT, sys.executable)]
        hide = [
            h
            for h in ("/home", "/root", "/run/user")
            if Path(h).is_dir() and not any(n.is_relative_to(h) for n in needed)
        ]
    hidden = tools_of_the_tests()  # a runtime-only install: the service must not need the test tools
    assert any(p.name == "pytest" for p in hidden) and any(p.name == "playwright" for p in hidden), hidden
    plan = {
        "probe": str(tmp_path),
        "hide_modules": poisoned(hidden, tmp_path / "poison"),
        "software": {"at": str(software), "entries": entries},
        "writable": [(str(s), str(t)) for s, t in writable],
        "private_tmp": yes(service, "PrivateTmp"),
        # a checkout in /tmp (a CI's): the venv's entry scripts name their interpreter by the venv's own path,
        # which the private /tmp covers; there the same venv (bound at software/.venv) is bound again
        "rebind": [
            (sys.prefix, str(software / ".venv"))
            for tmp in ("/tmp", "/var/tmp")
            if yes(service, "PrivateTmp") and Path(sys.prefix).is_relative_to(tmp)
        ],
        "hide": hide,
        "nofile": int(one(service, "LimitNOFILE", "0")),
        "cwd": str(cwd),
        "uid": uid,
        "gid": gid,
        "groups": groups,
        "no_new_privs": yes(service, "NoNewPrivileges"),
        "argv": argv,
        "env": env,
    }
    lines: list[str] = []
    with mount_points([software, *(t for _, t in writable)]):
        proc = subprocess.Popen(
            ["unshare", "-m", "--propagation", "private", sys.executable, str(ROOT / "tests" / "unit_sandbox.py"), json.dumps(plan)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
        )  # fmt: skip
        reader = threading.Thread(target=lambda: lines.extend(line.rstrip() for line in proc.stdout), daemon=True)
        reader.start()
        try:
            wait_for(lambda: any(READY.match(x) for x in lines) or proc.poll() is not None, 60, "the ready line", lines)
            assert proc.poll() is None, "run-cell serve ended before its ready line:\n" + "\n".join(lines[-30:])
            url = next(m.group(1) for x in lines if (m := READY.match(x)))
            assert url.startswith("https://"), url  # users: HTTPS, its certificate made in the cell's folder
            database = state / "data" / "history.sqlite"
            with httpx.Client(base_url=url, verify=False, timeout=60) as screen:
                login = screen.post("/api/login", json={"user": "eng1", "password": PASSWORD})
                assert login.status_code == 200, login.text
                csrf = {"x-csrf-token": login.json()["csrf"]}

                def command(name: str) -> None:
                    reply = screen.post(f"/api/command/{name}", headers=csrf)
                    assert reply.status_code == 200, reply.text

                command("StartContinuous")
                wait_for(lambda: picks(database) >= PICKS or proc.poll() is not None, 60, f"{PICKS} picks", lines)
                assert proc.poll() is None, "run-cell serve ended mid-shift:\n" + "\n".join(lines[-30:])
                # an engineer recalibrates from the screen at the safe point: the calibration is written
                # in the cell's folder, its deviation picture drawn (matplotlib) by the service
                command("Pause")
                wait_for(lambda: screen.get("/api/state").json()["paused"], 60, "the job paused", lines)
                report = screen.post("/api/recalibration/capture", headers=csrf)
                assert report.status_code == 200 and report.json()["passes"], report.text
                picture = screen.get(f"/api/recalibration/{report.json()['id']}/deviation.png")
                assert picture.content[:4] == b"\x89PNG", picture.text
                accept = screen.post(f"/api/recalibration/{report.json()['id']}/accept", headers=csrf)
                assert accept.status_code == 200 and accept.json()["accepted"], accept.text
                command("Resume")
            assert proc.poll() is None, "run-cell serve ended mid-shift:\n" + "\n".join(lines[-30:])
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            reader.join(10)
    output = "\n".join(lines)
    assert rc == 0, output[-3000:]
    assert "stopped: cell halted safely" in output, output[-3000:]
    assert picks(database) >= PICKS
    assert (state / "calibration" / "active.json").is_file()
    # everything it wrote is in the cell's folder or the cache, the service user's, and said nothing was refused
    serve_logs = sorted((state / "logs").glob("serve-*.log"))
    assert serve_logs, sorted(p.name for p in state.rglob("*"))
    refusals = [x for p in serve_logs for x in p.read_text().splitlines() if REFUSED_WRITE.search(x)]
    refusals += [x for x in lines if REFUSED_WRITE.search(x)]
    assert not refusals, "\n".join(refusals)
    made = [p for s, _ in writable for p in s.rglob("*")]
    assert not [p for p in made if p.stat().st_uid != uid and p != config_here], "files not the service user's"
    cache = [p.name for s, t in writable if t.is_relative_to("/var/cache") for p in s.rglob("*")]
    assert any(name.startswith("aspace-") for name in cache), cache  # the OPC UA address space kept for the next start
    assert any(name.startswith("plate-") for name in cache) and "fontlist" in " ".join(cache), cache
