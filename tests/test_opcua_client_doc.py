"""docs/opcua-client.md is true: its programs, exactly as printed, drive a real `run-cell serve`
secured as a plant's would be (users, Basic256Sha256 SignAndEncrypt, a client certificate the
cell trusts through its rejected/ -> trusted/ step, the HTTPS screen), the shipped sample
recipe is the one OPC 40100-1's GetRecipeListFiltered lists, and the method table is what the
server declares."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import ssl
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from asyncua import Client, ua

from cell.access.users import UserEntry, hash_password, write_users
from cell.core.events import Role
from tests.mv_harness import shared_cache_dir
from tests.probes import make_client_certificate
from tests.serve_process import ServeProcess
from tests.test_mv_node_opcua import node_modules  # noqa: F401  (the session's node-opcua-client install)

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "opcua-client.md"
MV = "http://opcfoundation.org/UA/MachineVision"
PASSWORD = "line-3 plc secret"
pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]


def block(language: str, first_line: str) -> str:
    """The doc's fenced code block in `language` whose text begins with `first_line`."""
    blocks = re.findall(rf"^```{language}\n(.*?)^```$", DOC.read_text(), re.S | re.M)
    found = [b for b in blocks if b.startswith(first_line)]
    assert len(found) == 1, f"one {language} block starting {first_line!r} in {DOC}"
    return found[0]


def secured_cell(work: Path, cache: Path) -> ServeProcess:
    """The simulated cell served as a plant's: a users file (so OPC UA needs a trusted certificate, a
    user and encryption, and the screen HTTPS and a login), the shipped recipes folder."""
    work.mkdir(parents=True, exist_ok=True)
    write_users(work / "users.json", [UserEntry("plc", Role.ENGINEER, hash_password(PASSWORD, 1000))])
    (work / "cell.toml").write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
        "[sim]\nreference_marks_mm = []\n"
        "[sim.feeder]\nparts_per_minute = 0\n"
        '[service]\ncapture_interval_s = 0.2\nusers_file = "users.json"\ncertificate_dir = "certs"\n'
        f'[service.machine_vision]\nrecipes_dir = "{REPO / "recipes"}"\nmodel_cache_dir = "{cache}"\n'
    )
    return ServeProcess(work, "--config", str(work / "cell.toml"), "--log-dir", str(work / "logs"))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """One secured cell for this module's clients (each leaves it Ready, its recipe unprepared)."""
    serve = secured_cell(tmp_path_factory.mktemp("secured") / "cell", shared_cache_dir(tmp_path_factory))
    yield serve
    assert serve.stop() == 0


def endpoint(serve: ServeProcess) -> str:
    return next(line.split("OPC UA ", 1)[1].split(";")[0] for line in serve.lines if line.startswith("ready:"))


def run(argv: list[str], env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=180, env=env, cwd=cwd)


def test_the_documented_python_client_and_screen_script_on_a_secured_cell(served, tmp_path):
    certs = served.workdir / "certs"
    key, cert, uri = asyncio.run(make_client_certificate(tmp_path / "plc", "plc-line-3"))
    program = tmp_path / "plc_sequence.py"
    program.write_text(block("python", '"""A PLC\'s sequence'))
    argv = [sys.executable, str(program), endpoint(served), "--recipe", "bolts-and-nuts", "--results", "2"]
    argv += ["--user", "plc", "--cert", str(cert), "--key", str(key), "--app-uri", uri]
    argv += ["--server-cert", str(certs / "server-cert.der")]
    env = {**os.environ, "CELL_PASSWORD": PASSWORD}

    # step 1.3: the first connection is refused and the certificate saved in rejected/; moved to trusted/
    refused = run(argv, env)
    assert refused.returncode != 0 and "recipes:" not in refused.stdout
    (saved,) = (certs / "rejected").iterdir()
    assert saved.read_bytes() == cert.read_bytes()
    (certs / "trusted").mkdir(exist_ok=True)
    shutil.move(saved, certs / "trusted" / saved.name)

    done = run(argv, env)
    assert done.returncode == 0, f"{done.stdout}\n{done.stderr[-3000:]}"
    out = done.stdout
    assert "vision system: Operational / Ready" in out
    assert "recipes: bolts-and-nuts\n" in out  # the shipped sample, listed by GetRecipeListFiltered
    assert "prepared bolts-and-nuts" in out
    job = re.search(r"^job (\S+) started$", out, re.M)
    assert job is not None, out
    assert len(re.findall(rf"^result {job[1]}/\d+: state 1, ", out, re.M)) == 2
    assert f"job {job[1]} ended: state 3" in out  # stopped with parts left: Aborted
    read_back = re.search(rf"^read back (\d+) of (\d+) results of job {job[1]} \(complete: True\)$", out, re.M)
    assert read_back is not None and read_back[1] == read_back[2] and int(read_back[1]) >= 3, out
    assert out.rstrip().endswith("done")

    screen_url = served.url
    script = tmp_path / "screen_api.py"
    script.write_text(block("python", '"""The operator screen'))
    ca = str(certs / "screen-cert.pem")
    shown = run(
        [sys.executable, str(script), screen_url, "--user", "plc", "--ca", ca, "--recipe", "bolts-and-nuts"], env
    )
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert shown.stdout.splitlines() == [
        "logged in: True",
        "prepare bolts-and-nuts: 200",
        "recipe in force: bolts-and-nuts",
        "unprepare: 200",
        "logged out: 200",
    ]
    # the header is what lets a control through: the same session without it is refused
    context = ssl.create_default_context(cafile=ca)
    login = urllib.request.Request(
        screen_url + "api/login",
        json.dumps({"user": "plc", "password": PASSWORD}).encode(),
        {"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(login, context=context, timeout=30) as reply:
        cookie = reply.headers["set-cookie"].split(";", 1)[0]
        token = json.loads(reply.read())["csrf"]
    for headers, status in (({}, 403), ({"X-CSRF-Token": "not-the-token"}, 403), ({"X-CSRF-Token": token}, 200)):
        recipe = urllib.request.Request(
            screen_url + "api/recipe",
            b'{"recipe_id": ""}',
            {"Content-Type": "application/json", "Cookie": cookie, **headers},
        )
        try:
            with urllib.request.urlopen(recipe, context=context, timeout=30) as reply:
                got = reply.status
        except urllib.error.HTTPError as e:
            got = e.code
            assert "CSRF" in json.loads(e.read())["error"]
        assert got == status, headers

    assert documented_methods() == asyncio.run(declared_methods(endpoint(served), key, cert, uri))


def documented_methods() -> list[str]:
    text = DOC.read_text()
    table = text.split("| object | method | inputs | outputs |\n|---|---|---|---|\n", 1)[1].split("\n\n", 1)[0]
    return sorted(table.splitlines())


async def declared_methods(url: str, key: Path, cert: Path, uri: str) -> list[str]:
    """Every method of the vision system's objects as a table row: its arguments' names and types."""
    client = Client(url, timeout=30, watchdog_intervall=15)
    client.application_uri = uri
    await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
    client.set_user("plc")
    client.set_password(PASSWORD)
    rows, names = [], {}
    async with client:
        mv = await client.get_namespace_index(MV)
        vs_type = await client.nodes.base_object_type.get_child([f"{mv}:VisionSystemType"])
        refs = await client.nodes.objects.get_references(
            refs=ua.ObjectIds.HierarchicalReferences, nodeclassmask=ua.NodeClass.Object
        )
        (vs,) = [client.get_node(r.NodeId) for r in refs if r.TypeDefinition == vs_type.nodeid]
        for path in (
            ["VisionStateMachine"],
            ["VisionStateMachine", "AutomaticModeStateMachine"],
            ["RecipeManagement"],
            ["ResultManagement"],
            ["SafetyStateManagement"],
        ):
            obj = await vs.get_child([f"{mv}:{p}" for p in path])
            for method in await obj.get_children(nodeclassmask=ua.NodeClass.Method):
                cells = []
                for which in ("InputArguments", "OutputArguments"):
                    try:
                        arguments = await (await method.get_child([f"0:{which}"])).read_value()
                    except ua.UaStatusCodeError:
                        arguments = []
                    shown = []
                    for a in arguments:
                        if a.DataType not in names:
                            names[a.DataType] = (await client.get_node(a.DataType).read_browse_name()).Name
                        shown.append(f"{a.Name}: {names[a.DataType]}{'[]' if a.ValueRank == 1 else ''}")
                    cells.append(", ".join(shown) or "(none)")
                name = (await method.read_browse_name()).Name
                rows.append(f"| {path[-1]} | `{name}` | {cells[0]} | {cells[1]} |")
    return sorted(rows)


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed: the node-opcua program is not run")
def test_the_documented_node_opcua_client_on_a_secured_cell(served, tmp_path, node_modules):  # noqa: F811
    certs = served.workdir / "certs"
    program = tmp_path / "plc_sequence.cjs"
    program.write_text(block("js", "// The same PLC sequence"))
    home = node_modules.parent  # node-opcua's own PKI folder: made once, kept with the install (not ~)
    env = {
        **os.environ,
        "HOME": str(home),
        "XDG_CONFIG_HOME": str(home / ".config"),
        "NODE_PATH": str(node_modules),
    }
    key, cert, uri = asyncio.run(make_client_certificate(tmp_path / "plc", "plc-node"))
    env |= {"CELL_USER": "plc", "CELL_PASSWORD": PASSWORD, "CELL_CERT": str(cert), "CELL_KEY": str(key)}
    env["CELL_APP_URI"] = uri  # the application URI in the certificate
    (certs / "trusted").mkdir(exist_ok=True)  # trusted as step 1.3 says (the refusal first: the Python test)
    shutil.copy(cert, certs / "trusted" / "plc-node.der")
    argv = ["node", str(program), endpoint(served), "bolts-and-nuts", "2"]
    done = run(argv, env)
    assert done.returncode == 0, f"{done.stdout}\n{done.stderr[-3000:]}"
    out = done.stdout
    assert "recipes: bolts-and-nuts\n" in out and "prepared bolts-and-nuts" in out
    job = re.search(r"^job (\S+) started$", out, re.M)
    assert job is not None, out
    assert len(re.findall(rf"^result {job[1]}/\d+: state 1$", out, re.M)) == 2
    assert f"job {job[1]} ended: Ready" in out
    assert re.search(rf"^read back (\d+) of \1 results of job {job[1]} \(complete: true\)$", out, re.M), out
    assert out.rstrip().endswith("done")
