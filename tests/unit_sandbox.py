"""Start a command as a systemd unit would, without systemd: tests/test_unit_file.py's harness.

`parse_unit(text)` reads a unit file (sections, repeated keys, `\\` continuations, comments).
`main()` runs under `unshare -m` (a mount namespace of its own, as root) with a JSON plan on
argv[1]: it makes every mount read-only (`ProtectSystem=strict`: all but /proc, /sys, /dev),
lays the software read-only where the unit's ExecStart expects it, binds each of the unit's
writable folders (StateDirectory=, CacheDirectory=, RuntimeDirectory=, ReadWritePaths=) to a
folder of the test, mounts an empty /tmp and /var/tmp (`PrivateTmp=yes`), hides /home, /root and
/run/user (`ProtectHome=yes`), enters WorkingDirectory= and then becomes the unit's user with
setpriv (NoNewPrivileges=) and execs ExecStart with the unit's environment. Nothing outside the
namespace changes (the test makes and removes the mount points). The test tools (pyproject.toml's
[test] extra, and what only they pull in) are hidden behind stand-ins that raise ImportError: the
service runs as on a line PC's runtime-only install.
"""

from __future__ import annotations

import json
import os
import resource
import shlex
import subprocess
import sys
from pathlib import Path

API_FILESYSTEMS = ("/proc", "/sys", "/dev")  # ProtectSystem=strict leaves these as they are


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """{section: {key: [values, in order]}}; an empty assignment (`Key=`) resets the key's list, as systemd does."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    pending = ""
    for raw in text.splitlines():
        line = pending + raw.strip()
        pending = ""
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        if current is None or "=" not in line:
            raise ValueError(f"not a unit file line: {raw!r}")
        key, value = (part.strip() for part in line.split("=", 1))
        if value == "":
            current[key] = []
        else:
            current.setdefault(key, []).append(value)
    return sections


def environment(values: list[str]) -> dict[str, str]:
    """Environment= lines: space-separated KEY=VALUE words, quoted as in a shell."""
    env: dict[str, str] = {}
    for value in values:
        for word in shlex.split(value):
            key, _, val = word.partition("=")
            env[key] = val
    return env


def words(values: list[str]) -> list[str]:
    """A list setting (ReadWritePaths=, SupplementaryGroups=, StateDirectory= ...): every word of every line."""
    return [w for value in values for w in shlex.split(value)]


def mount(*args: str) -> None:
    subprocess.run(["mount", *args], check=True)


def _mount_points() -> list[str]:
    points = []
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        point = line.split()[4].encode().decode("unicode_escape")  # \040 for a space
        if not any(point == api or point.startswith(api + "/") for api in API_FILESYSTEMS):
            points.append(point)
    return points


def main() -> None:
    plan = json.loads(sys.argv[1])
    mount("--make-rprivate", "/")
    for point in _mount_points():  # ProtectSystem=strict
        subprocess.run(["mount", "-o", "remount,bind,ro", point], check=False, stderr=subprocess.DEVNULL)
    try:  # the test's own folder lies on a mount made read-only just now
        Path(plan["probe"], "written-through-protect-system").touch()
    except OSError:
        pass
    else:
        raise SystemExit(f"unit_sandbox: {plan['probe']} is still writable after remounting every mount read-only")
    for stand_in, module in plan["hide_modules"]:  # a runtime-only install: the test tools are not there
        mount("--bind", stand_in, module)
    # the software, read-only where ExecStart expects it: each entry of the checkout, and the venv as .venv
    software = plan["software"]
    mount("-t", "tmpfs", "-o", "mode=0755", "tmpfs", software["at"])
    for name, source in software["entries"].items():
        target = Path(software["at"], name)
        if Path(source).is_dir():
            target.mkdir()
        else:
            target.touch()
        mount("--bind", source, str(target))
        mount("-o", "remount,bind,ro", str(target))
    mount("-o", "remount,ro", software["at"])
    for source, target in plan["writable"]:  # StateDirectory=, CacheDirectory=, RuntimeDirectory=, ReadWritePaths=
        mount("--bind", source, target)
        mount("-o", "remount,bind,rw", target)
    if plan["private_tmp"]:
        for tmp in ("/tmp", "/var/tmp"):
            mount("-t", "tmpfs", "-o", "mode=1777", "tmpfs", tmp)
    for original, alias in plan.get("rebind", []):  # a venv of a checkout in /tmp: its scripts' #! names it
        Path(original).mkdir(parents=True, exist_ok=True)
        mount("--bind", alias, original)
        mount("-o", "remount,bind,ro", original)
    for hidden in plan["hide"]:  # ProtectHome=yes
        mount("-t", "tmpfs", "-o", "ro,mode=0755", "tmpfs", hidden)
    if plan["nofile"]:
        resource.setrlimit(resource.RLIMIT_NOFILE, (plan["nofile"], plan["nofile"]))
    os.chdir(plan["cwd"])
    groups = ",".join(str(g) for g in plan["groups"])
    setpriv = [
        "setpriv",
        f"--reuid={plan['uid']}",
        f"--regid={plan['gid']}",
        f"--groups={groups}" if groups else "--clear-groups",
        *(["--no-new-privs"] if plan["no_new_privs"] else []),
        "--",
    ]
    os.execvpe("setpriv", setpriv + plan["argv"], plan["env"])


if __name__ == "__main__":
    main()
