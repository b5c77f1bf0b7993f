"""The Machine Vision address space: the shipped NodeSets, the cache that keeps start-up fast
(cold and warm give the same model; a corrupt, foreign or stale cache is rebuilt, never a
failed start), and every Mandatory child of the types we instantiate present on the instance."""

from __future__ import annotations

import asyncio
import hashlib
import logging
import pickle
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from asyncua import Client, Server, ua

from cell.service import mv_addressspace as mva
from tests.mv_harness import MachineVisionHarness, shared_cache_dir

UANS = {"u": "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"}


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return shared_cache_dir(tmp_path_factory)


def _load(cache: Path | None) -> tuple[mva.ModelLoad, Server]:
    async def run() -> tuple[mva.ModelLoad, Server]:
        server = Server()
        return await mva.init_server_with_models(server, cache), server

    return asyncio.run(run())


def _model_nodes(server: Server) -> dict[str, str]:
    """Every node of the two models (and the standard ones) by NodeId: its BrowseName."""
    aspace = server.iserver.aspace
    out = {}
    for nid in aspace.keys():
        bn = aspace[nid].attributes[ua.AttributeIds.BrowseName].value.Value.Value
        out[nid.to_string()] = f"{bn.NamespaceIndex}:{bn.Name}"
    return out


def test_nodesets_are_shipped_with_their_licence_and_provenance() -> None:
    folder = mva.nodeset_dir()
    readme = (folder / "README.md").read_text()
    for name in mva.NODESET_FILES:
        text = (folder / name).read_text(encoding="utf-8")
        assert "OPC Foundation MIT License 1.00" in text.split("<UANodeSet", 1)[0], name
        assert hashlib.sha256(text.encode()).hexdigest() in readme, f"{name}'s hash in the README"
    assert "a2d4ae8b337ff9f014878fc88f9b6acda0ff3674" in readme
    assert (
        'ModelUri="http://opcfoundation.org/UA/MachineVision" Version="1.0.0"'
        in (folder / "Opc.Ua.MachineVision.NodeSet2.xml").read_text()
    )


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_warm_start_loads_the_same_address_space_as_the_xml(cache_dir: Path, tmp_path: Path) -> None:
    cold, cold_server = _load(None)
    warm, warm_server = _load(cache_dir)
    assert (cold.source, warm.source) == ("xml", "cache")
    assert cold.namespaces == warm.namespaces == mva.EXPECTED_NAMESPACES
    assert _model_nodes(cold_server) == _model_nodes(warm_server)
    for name in ("ResultDataType", "RecipeIdExternalDataType", "SystemStateDescriptionDataType"):
        cls = getattr(ua, name)
        assert cls.__name__ == name, f"{name} has its own class (own encoding), not its parent's"


def _damage(path: Path, damage: str) -> None:
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "flipped byte":
        path.write_bytes(data[:-100] + bytes([data[-100] ^ 0xFF]) + data[-99:])
    elif damage == "not ours":
        path.write_bytes(b"GIF89a" + data[6:])
    else:
        payload = pickle.dumps({"x": 1} if damage.startswith("valid") else {"namespaces": print, "nodes": {}})
        path.write_bytes(mva._MAGIC + hashlib.sha256(payload).digest() + payload)


@pytest.mark.slow  # its fixture builds the shared cache (once per run)
@pytest.mark.timeout(180)
@pytest.mark.parametrize(
    "damage",
    ["truncated", "flipped byte", "not ours", "valid checksum, wrong content", "unknown class in the pickle"],
)
def test_a_damaged_cache_is_refused_before_anything_is_loaded(damage: str, cache_dir: Path, tmp_path: Path) -> None:
    original = cache_dir / f"aspace-{mva.cache_key()}.pickle"
    path = tmp_path / original.name
    shutil.copyfile(original, path)
    assert set(mva.read_cache(path)) == {"namespaces", "nodes"}, "the undamaged copy reads"
    _damage(path, damage)
    with pytest.raises((ValueError, pickle.UnpicklingError, EOFError)):
        mva.read_cache(path)


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_bad_or_stale_cache_is_rebuilt_not_a_failed_start(
    cache_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    mine = tmp_path / "cache"
    mine.mkdir()
    path = mine / f"aspace-{mva.cache_key()}.pickle"
    shutil.copyfile(cache_dir / path.name, path)
    stale = mine / "aspace-000000000000000000000000.pickle"  # another NodeSet or asyncua version's
    shutil.copyfile(path, stale)
    _damage(path, "truncated")
    with caplog.at_level(logging.WARNING, logger="cell.service.mv_addressspace"):
        load, server = _load(mine)
    assert load.source == "xml" and "unusable" in load.note
    assert any("unusable" in r.getMessage() for r in caplog.records), "the bad cache is logged"
    assert "3:VisionSystemType" in _model_nodes(server).values()
    assert [p.name for p in mine.glob("aspace-*.pickle")] == [path.name], "rebuilt; the stale one removed"
    assert _load(mine)[0].source == "cache", "the rebuilt cache is used on the next start"


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_cache_that_cannot_be_written_is_only_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder should be")
    with caplog.at_level(logging.WARNING, logger="cell.service.mv_addressspace"):
        load, _ = _load(blocker / "cache")
    assert load.source == "xml"
    assert any("not written" in r.getMessage() for r in caplog.records)


# ---- every Mandatory child of the types we instantiate -------------------------------------
class NodeSet:
    """The shipped NodeSet XML, read with nothing but the standard library."""

    def __init__(self, path: Path):
        root = ET.parse(path).getroot()
        self.uri = root.find("u:NamespaceUris/u:Uri", UANS).text
        self.nodes = {el.get("NodeId"): el for el in root if el.get("NodeId")}
        self.by_name = {el.get("BrowseName"): nid for nid, el in self.nodes.items() if el.tag.endswith("Type")}

    def refs(self, nid: str) -> list[ET.Element]:
        el = self.nodes[nid].find("u:References", UANS)
        return [] if el is None else list(el)

    def mandatory_children(self, nid: str) -> list[str]:
        """Mandatory InstanceDeclarations of a type or declaration, and of its supertypes in this NodeSet."""
        out = []
        for r in self.refs(nid):
            forward = r.get("IsForward", "true") != "false"
            if forward and r.get("ReferenceType") in ("HasComponent", "HasProperty", "HasOrderedComponent"):
                child = r.text
                if child in self.nodes and any(
                    c.get("ReferenceType") == "HasModellingRule" and c.text == "i=78" for c in self.refs(child)
                ):
                    out.append(child)
            if not forward and r.get("ReferenceType") == "HasSubtype" and r.text in self.nodes:
                out.extend(self.mandatory_children(r.text))
        return out

    def type_definition(self, nid: str) -> str | None:
        return next((r.text for r in self.refs(nid) if r.get("ReferenceType") == "HasTypeDefinition"), None)


async def _missing(client: Client, ns: NodeSet, node, decl_or_type: str, path: str) -> list[str]:
    mv_index = await client.get_namespace_index(ns.uri)
    missing = []
    for child in ns.mandatory_children(decl_or_type):
        browse_name = ns.nodes[child].get("BrowseName")  # "1:Name" in the model's namespace, "Name" in OPC UA's
        name = browse_name.split(":", 1)[-1]
        qualified = f"{mv_index}:{name}" if browse_name.startswith("1:") else f"0:{name}"
        try:
            instance = await node.get_child([qualified])
        except ua.UaStatusCodeError:
            missing.append(f"{path}/{name}")
            continue
        missing += await _missing(client, ns, instance, child, f"{path}/{name}")
        tdef = ns.type_definition(child)
        if tdef in ns.nodes:
            missing += await _missing(client, ns, instance, tdef, f"{path}/{name}")
    return missing


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_every_mandatory_child_of_the_instantiated_types_exists(cache_dir: Path, tmp_path: Path) -> None:
    mv = NodeSet(mva.nodeset_dir() / "Opc.Ua.MachineVision.NodeSet2.xml")
    harness = MachineVisionHarness(tmp_path, cache_dir).start()

    async def walk() -> list[str]:
        async with Client(harness.endpoint, timeout=30, watchdog_intervall=15) as client:
            mv_index = await client.get_namespace_index(mv.uri)
            vs = client.get_node(harness.mv.node.nodeid)
            assert (await vs.read_type_definition()) == ua.NodeId(1003, mv_index)
            missing = await _missing(client, mv, vs, mv.by_name["1:VisionSystemType"], "VisionSystem")
            recipes = await vs.get_child([f"{mv_index}:RecipeManagement", f"{mv_index}:Recipes"])
            recipe_objects = await recipes.get_children()
            assert len(recipe_objects) == 2, "the two recipes of the harness' book"
            for recipe in recipe_objects:
                missing += await _missing(client, mv, recipe, mv.by_name["1:RecipeType"], "Recipes/<Recipe>")
            # the optional parts we implement are there too
            for path in (
                ["VisionStateMachine", "AutomaticModeStateMachine"],
                ["ResultManagement", "ReleaseResultHandle"],
            ):
                await vs.get_child([f"{mv_index}:{p}" for p in path])
            return missing

    try:
        assert asyncio.run(walk()) == []
    finally:
        harness.stop()


def test_the_cache_folder_follows_the_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cell.service.mv_config import MachineVisionConfig

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert mva.cache_dir_for(MachineVisionConfig()) == tmp_path / "xdg" / "pick-cell" / "opcua"
    assert mva.cache_dir_for(MachineVisionConfig(model_cache_dir=tmp_path / "c")) == tmp_path / "c"
    assert mva.cache_dir_for(MachineVisionConfig(model_cache=False)) is None
