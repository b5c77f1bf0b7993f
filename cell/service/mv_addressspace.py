"""Build an asyncua server's address space with the OPC Foundation's NodeSets (DI, Machine
Vision) in it, fast: the XML import is done once and its result cached.

`import_xml` of the two NodeSets costs about as much CPU as the standard address space itself
(most of it asyncua adding references one at a time). The cold path does exactly that, then
pickles the whole address space (standard nodes, DI, Machine Vision) into the cache folder
under a name keyed by the NodeSet files' hash, asyncua's version and Python's, in chunks of
nodes (so that loading it leaves no holes behind: _cache_payload). The warm path unpickles it
in place of asyncua's standard address space, inside `Server.init()`, with the garbage
collector paused (pickle builds a few hundred thousand small objects; the collector
would otherwise run over them again and again).

What cannot be pickled by name, the structure and enumeration classes asyncua generates from
the NodeSets' DataTypeDefinitions at run time, is stored as a placeholder (type name and
fields) and rebuilt once `load_data_type_definitions` has made the classes again.

The cache is only a speed-up: a missing, truncated, corrupt or stale file is logged once and
rebuilt from the XML, never a failed start. Everything is checked before the server's address
space is touched (a digest of the payload, then its shape), so a bad file never leaves half
a model behind. Cache files hold pickles: the folder must be writable only by the service's
user (the default is under the user's own cache folder).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import gc
import hashlib
import io
import logging
import pickle
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import asyncua
from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace, AttributeValue, NodeData

from cell.atomicfile import write_bytes_atomic
from cell.cachedir import user_cache_dir
from cell.errors import OutputError
from cell.service.mv_config import MachineVisionConfig
from cell.service.ua_values import node_id

log = logging.getLogger(__name__)

DI_URI = "http://opcfoundation.org/UA/DI/"
MV_URI = "http://opcfoundation.org/UA/MachineVision"
NODESET_FILES = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.MachineVision.NodeSet2.xml")  # in import order
MODEL_URIS = (DI_URI, MV_URI)
# After Server.init() the namespace array is [OPC UA, the application URI]; the models come next.
EXPECTED_NAMESPACES = {DI_URI: 2, MV_URI: 3}
_FORMAT = 3  # bump when what the cache holds changes
_CHUNK_NODES = 256  # nodes per pickle in the cache (see _cache_payload)
_MAGIC = b"pick-cell aspace cache\n"
_DYNAMIC_MODULE = "asyncua.common.structures104"  # where asyncua puts the classes it generates


@dataclass(frozen=True)
class ModelLoad:
    """What `init_server_with_models` did: for the log and the start-up figures."""

    source: str  # "cache" | "xml"
    cache_file: Path | None
    cpu_s: float  # CPU time of init + model load
    namespaces: dict[str, int]  # URI -> namespace index
    note: str = ""  # why the cache was not used, if it was not


def nodeset_dir() -> Path:
    return Path(str(resources.files("cell.service") / "nodesets"))


def cache_key(folder: Path | None = None) -> str:
    """The NodeSets' content, asyncua's and Python's versions and this format: any change, a new file."""
    h = hashlib.sha256()
    for name in NODESET_FILES:
        h.update(((folder or nodeset_dir()) / name).read_bytes())
    h.update(f"{asyncua.__version__}|{sys.version_info[:3]}|{_FORMAT}".encode())
    return h.hexdigest()[:24]


def default_cache_dir() -> Path:
    return user_cache_dir("opcua")


def cache_dir_for(mv: MachineVisionConfig) -> Path | None:
    """The cache folder `[service.machine_vision]` asks for (None: no cache)."""
    if not mv.model_cache:
        return None
    return mv.model_cache_dir or default_cache_dir()


async def init_server_with_models(server: Server, cache_dir: Path | None) -> ModelLoad:
    """`server.init()` with DI and Machine Vision loaded; call it on a new Server instead of
    `init()`, before registering any namespace of one's own. `cache_dir` None: no cache."""
    t0 = time.process_time()
    cache_file = cache_dir / f"aspace-{cache_key()}.pickle" if cache_dir is not None else None
    warm = _WarmLoad(server, cache_file)
    warm.install()
    await server.init()
    if warm.nodes_loaded:
        namespaces = await _register_models(server)
        if namespaces != warm.namespaces:  # only if asyncua changed how init() fills the namespace array
            raise RuntimeError(f"cached model namespaces {warm.namespaces}, but the server gave {namespaces}")
        await _load_classes(server)
        warm.resolve_placeholders()
        return ModelLoad("cache", cache_file, time.process_time() - t0, namespaces)
    namespaces = await _import_xml(server)
    if namespaces != EXPECTED_NAMESPACES:
        raise RuntimeError(f"model namespaces {namespaces}: call init_server_with_models on a new Server")
    _complete_definitions(server)
    _forget_aliases(server)
    await _load_classes(server)
    if cache_file is not None:
        _write_cache(server, cache_file, namespaces)
    return ModelLoad("xml", cache_file, time.process_time() - t0, namespaces, warm.note)


async def _load_classes(server: Server) -> None:
    """Make the Python classes of the models' DataTypes (every one has a definition by now)."""
    await server.load_data_type_definitions()


def _complete_definitions(server: Server) -> int:
    """Give every structure DataType of the models a DataTypeDefinition. The NodeSets leave it
    empty where a subtype adds no field (RecipeIdExternalDataType, ConfigurationIdDataType ...
    under the abstract BinaryIdBaseDataType; DI's abstract FetchResultDataType); OPC 10000-3
    has the definition carry the inherited fields, and clients (node-opcua) need it to encode
    and decode those types with their own encodings. Returns how many were completed."""
    aspace = server.iserver.aspace
    todo = [nid for nid in aspace.keys() if nid.NamespaceIndex in EXPECTED_NAMESPACES.values()]
    todo = [n for n in todo if _attr(aspace[n], ua.AttributeIds.NodeClass) == ua.NodeClass.DataType]
    done = 0
    for _ in range(8):  # parents first: a chain of subtypes needs one pass per level
        progress = False
        for nid in todo:
            ndata = aspace[nid]
            if _attr(ndata, ua.AttributeIds.DataTypeDefinition) is not None:
                continue
            parent = _parent(ndata)
            base = _structure_base(aspace, parent)
            if base is None:
                continue  # not a structure, or its parent is not complete yet
            sdef = ua.StructureDefinition(
                DefaultEncodingId=_default_encoding(aspace, ndata),
                BaseDataType=parent,
                StructureType=base.StructureType,
                Fields=list(base.Fields),
            )
            ndata.attributes[ua.AttributeIds.DataTypeDefinition] = AttributeValue(ua.DataValue(ua.Variant(sdef)))
            done += 1
            progress = True
        if not progress:
            break
    return done


def _forget_aliases(server: Server) -> None:
    """The XML import made the definition-less subtypes aliases of their parents' classes;
    forget those, so the classes are made again from the completed definitions."""
    aspace = server.iserver.aspace
    for nid in [n for n in aspace.keys() if n.NamespaceIndex in EXPECTED_NAMESPACES.values()]:
        if _attr(aspace[nid], ua.AttributeIds.NodeClass) != ua.NodeClass.DataType:
            continue
        name = _attr(aspace[nid], ua.AttributeIds.BrowseName).Name
        cls = getattr(ua, name, None)
        if cls is not None and getattr(cls, "data_type", nid) != nid:
            delattr(ua, name)
            ua.extension_objects_by_datatype.pop(nid, None)


def _parent(ndata: NodeData) -> ua.NodeId | None:
    return next((r.NodeId for r in ndata.references if r.ReferenceTypeId == _HAS_SUBTYPE and not r.IsForward), None)


def _structure_base(aspace: AddressSpace, parent: ua.NodeId | None) -> ua.StructureDefinition | None:
    """The parent's definition if the parent is a structure (Structure itself: an empty one)."""
    if parent is None:
        return None
    if parent == node_id(ua.ObjectIds.Structure):
        return ua.StructureDefinition(BaseDataType=parent, StructureType=ua.StructureType.Structure, Fields=[])
    if parent not in aspace:
        return None
    sdef = _attr(aspace[parent], ua.AttributeIds.DataTypeDefinition)
    return sdef if isinstance(sdef, ua.StructureDefinition) else None


def _default_encoding(aspace: AddressSpace, ndata: NodeData) -> ua.NodeId:
    for r in ndata.references:
        target: ua.NodeId = r.NodeId  # an ExpandedNodeId; asyncua's annotation of the field reads as Any
        if r.ReferenceTypeId == _HAS_ENCODING and r.IsForward and target in aspace:
            if _attr(aspace[target], ua.AttributeIds.BrowseName).Name == "Default Binary":
                return target
    return ua.NodeId()


_HAS_ENCODING = node_id(ua.ObjectIds.HasEncoding)
_HAS_SUBTYPE = node_id(ua.ObjectIds.HasSubtype)


def _attr(ndata: NodeData, attr: ua.AttributeIds) -> Any:
    a = ndata.attributes.get(attr)
    return None if a is None or a.value is None or a.value.Value is None else a.value.Value.Value


async def _register_models(server: Server) -> dict[str, int]:
    return {uri: await server.register_namespace(uri) for uri in MODEL_URIS}


async def _import_xml(server: Server) -> dict[str, int]:
    quiet = logging.getLogger("asyncua.common.xmlimporter")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # it warns about every DataType it cannot map to a Python class
    try:
        for name in NODESET_FILES:
            await server.import_xml(str(nodeset_dir() / name))
    finally:
        quiet.setLevel(level)
    return {uri: await server.get_namespace_index(uri) for uri in MODEL_URIS}


# ---- the cache file -----------------------------------------------------------------
@dataclass
class _Placeholder:
    """A value of a class asyncua generates at run time, until that class exists again."""

    type_name: str
    state: Any  # dict of fields (a structure) or int (an enumeration)
    is_enum: bool = False


def _is_generated(cls: type) -> bool:
    return cls.__module__ == _DYNAMIC_MODULE and getattr(sys.modules[_DYNAMIC_MODULE], cls.__name__, None) is not cls


def _to_placeholder(value: Any) -> Any:
    """`value` with every instance of a generated class replaced by a placeholder (nested too)."""
    if isinstance(value, list):
        return [_to_placeholder(v) for v in value]
    cls = type(value)
    if not _is_generated(cls):
        return value
    if isinstance(value, enum.Enum):
        return _Placeholder(cls.__name__, int(value.value), True)
    state = {f.name: _to_placeholder(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return _Placeholder(cls.__name__, state)


def _holds_generated(value: Any) -> bool:
    if isinstance(value, list):
        return any(_holds_generated(v) for v in value)
    return _is_generated(type(value))


@contextlib.contextmanager
def _values_swapped(aspace: AddressSpace) -> Iterator[None]:
    """While inside: the address space's values of generated classes are placeholders, and no
    method has its callback (asyncua's own dump drops them too; they are bound again at start)."""
    swapped: list[tuple[Any, Any]] = []
    calls = {nid: nd.call for nid, nd in aspace._nodes.items() if nd.call is not None}
    try:
        for nid in calls:
            aspace._nodes[nid].call = None
        for ndata in aspace._nodes.values():
            attr = ndata.attributes.get(ua.AttributeIds.Value)
            if attr is None or attr.value is None or attr.value.Value is None:
                continue
            if _holds_generated(attr.value.Value.Value):
                swapped.append((attr, attr.value))
                variant = attr.value.Value
                attr.value = dataclasses.replace(
                    attr.value, Value=dataclasses.replace(variant, Value=_to_placeholder(variant.Value))
                )
        yield
    finally:
        for attr, original in swapped:
            attr.value = original
        for nid, call in calls.items():
            aspace._nodes[nid].call = call


class _Unpickler(pickle.Unpickler):
    """Only what an address space holds: asyncua's types, our placeholder, plain Python values."""

    _ALLOWED_MODULES = ("asyncua.", "datetime", "uuid", "collections", "enum", "builtins", "copyreg", "dateutil")

    def find_class(self, module: str, name: str) -> Any:
        if module == __name__ and name == "_Placeholder":
            return _Placeholder
        if module == "builtins" and name not in _SAFE_BUILTINS:
            raise pickle.UnpicklingError(f"unexpected {module}.{name} in the address space cache")
        if module.startswith(self._ALLOWED_MODULES):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"unexpected {module}.{name} in the address space cache")


_SAFE_BUILTINS = {
    "set",
    "frozenset",
    "list",
    "dict",
    "tuple",
    "bytearray",
    "bytes",
    "int",
    "float",
    "str",
    "bool",
    "complex",
}


def _write_cache(server: Server, path: Path, namespaces: dict[str, int]) -> None:
    """Pickle the address space now, before the application adds its nodes; a failure is logged, never raised."""
    aspace = server.iserver.aspace
    try:
        with _values_swapped(aspace):
            payload = _cache_payload(namespaces, aspace._nodes)
    except Exception as e:  # noqa: BLE001 - a cache we cannot make is only slower starts
        log.warning("address space cache not written (%s): %s", path, e)
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        write_bytes_atomic(path, _MAGIC + hashlib.sha256(payload).digest() + payload)
    except (OSError, OutputError) as e:
        log.warning("address space cache not written (%s): %s", path, e)
        return
    for old in path.parent.glob("aspace-*.pickle"):
        if old != path:
            with contextlib.suppress(OSError):
                old.unlink()  # another NodeSet or asyncua version's: stale
    log.info("address space cache written: %s (%d kB)", path, len(payload) // 1024)


def _cache_payload(namespaces: dict[str, int], nodes: dict[ua.NodeId, NodeData]) -> bytes:
    """The address space as a header and then one pickle per _CHUNK_NODES nodes.

    One pickle of the whole address space made its load hold every temporary object the
    unpickler makes (hundreds of thousands of small tuples and dicts, the slots' state), all
    remembered until the end and then freed among the live nodes: about 120 MB that stayed in
    the process, in holes, for good. Chunk by chunk, each chunk's temporaries are freed before
    the next chunk is read, which builds its nodes in their place."""
    out = io.BytesIO()
    items = list(nodes.items())
    chunks = [items[i : i + _CHUNK_NODES] for i in range(0, len(items), _CHUNK_NODES)]
    pickle.dump({"namespaces": namespaces, "chunks": len(chunks)}, out, protocol=pickle.HIGHEST_PROTOCOL)
    for chunk in chunks:
        pickle.dump(chunk, out, protocol=pickle.HIGHEST_PROTOCOL)
    return out.getvalue()


def _load_payload(payload: bytes) -> dict[str, Any]:
    """What _cache_payload wrote: {"namespaces", "nodes"}; ValueError when it is not that."""
    stream = io.BytesIO(payload)
    head = _Unpickler(stream).load()
    if not isinstance(head, dict) or set(head) != {"namespaces", "chunks"} or not isinstance(head["chunks"], int):
        raise ValueError("unexpected content")
    nodes: dict[Any, Any] = {}
    for _ in range(head["chunks"]):
        chunk = _Unpickler(stream).load()  # a fresh memo each: the last chunk's temporaries are gone
        if not isinstance(chunk, list):
            raise ValueError("unexpected content")
        nodes.update(chunk)
        del chunk
    if stream.read(1):
        raise ValueError("unexpected content after the last chunk")
    return {"namespaces": head["namespaces"], "nodes": nodes}


def read_cache(path: Path) -> dict[str, Any]:
    """The cache's content, checked; ValueError (or an unpickling error) when it is not one:
    `init_server_with_models` then rebuilds it."""
    data = path.read_bytes()
    if not data.startswith(_MAGIC):
        raise ValueError("not an address space cache")
    digest, payload = data[len(_MAGIC) : len(_MAGIC) + 32], data[len(_MAGIC) + 32 :]
    if hashlib.sha256(payload).digest() != digest:
        raise ValueError("checksum mismatch (truncated or corrupt)")
    del data
    with _gc_paused():
        content = _load_payload(payload)
    return _check_shape(content)


def _check_shape(content: object) -> dict[str, Any]:
    """The cache's content, once it has the expected shape; ValueError if not."""
    if not isinstance(content, dict) or set(content) != {"namespaces", "nodes"}:
        raise ValueError("unexpected content")
    namespaces, nodes = content["namespaces"], content["nodes"]
    if namespaces != EXPECTED_NAMESPACES:
        raise ValueError(f"model namespaces {namespaces}, expected {EXPECTED_NAMESPACES}")
    if not isinstance(nodes, dict) or not nodes:
        raise ValueError("no nodes")
    vision_system_type = node_id(1003, namespaces[MV_URI])
    for nid in (node_id(ua.ObjectIds.ObjectsFolder), node_id(ua.ObjectIds.Server), vision_system_type):
        if nid not in nodes:
            raise ValueError(f"node {nid.to_string()} missing")
    return content


@contextlib.contextmanager
def _gc_paused() -> Iterator[None]:
    """No collection while pickle builds the address space's objects; then they are frozen (they
    live as long as the server: later collections need not scan them again)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if was:
            gc.enable()


class _WarmLoad:
    """Stands in for asyncua's standard address space loader during `Server.init()`: the cached
    address space if there is a good one, else asyncua's own loader (and the caller imports the XML)."""

    def __init__(self, server: Server, path: Path | None):
        self.server, self.path = server, path
        self.nodes_loaded = False
        self.namespaces: dict[str, int] = {}
        self.note = "no cache folder" if path is None else ""
        self._placeholders: list[ua.NodeId] = []

    def install(self) -> None:
        iserver = self.server.iserver
        original = iserver.load_standard_address_space

        async def load(shelf_file: Path | None = None) -> None:
            if self._load():
                return
            await original(shelf_file)

        iserver.load_standard_address_space = load  # type: ignore[method-assign]  # asyncua's loader, replaced on purpose

    def _load(self) -> bool:
        if self.path is None:
            return False
        if not self.path.exists():
            self.note = "first start: no cache yet"
            return False
        try:
            content = read_cache(self.path)
        except Exception as e:  # noqa: BLE001 - any bad cache is rebuilt
            self.note = f"cache {self.path} unusable ({type(e).__name__}: {e}): rebuilt"
            log.warning("OPC UA address space %s", self.note)
            with contextlib.suppress(OSError):
                self.path.unlink()
            return False
        self.server.iserver.aspace._nodes = content["nodes"]
        self.namespaces = content["namespaces"]
        self.nodes_loaded = True
        return True

    def resolve_placeholders(self) -> None:
        """Rebuild the values that were stored as placeholders, now that asyncua made their classes again."""
        for ndata in self.server.iserver.aspace._nodes.values():
            attr = ndata.attributes.get(ua.AttributeIds.Value)
            if attr is None or attr.value is None or attr.value.Value is None:
                continue
            value = attr.value.Value.Value
            if not _holds_placeholder(value):
                continue
            variant = attr.value.Value
            attr.value = dataclasses.replace(attr.value, Value=dataclasses.replace(variant, Value=_resolve(value)))


def _holds_placeholder(value: Any) -> bool:
    if isinstance(value, _Placeholder):
        return True
    if isinstance(value, list):
        return any(_holds_placeholder(v) for v in value)
    return False


def _resolve(value: Any) -> Any:
    if isinstance(value, list):
        return [_resolve(v) for v in value]
    if isinstance(value, dict):
        return {k: _resolve(v) for k, v in value.items()}
    if not isinstance(value, _Placeholder):
        return value
    cls = getattr(ua, value.type_name)
    if value.is_enum:
        return cls(value.state)
    return cls(**{k: _resolve(v) for k, v in value.state.items()})
