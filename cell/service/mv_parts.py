"""What the parts of the OPC 40100-1 Machine Vision server share: the typed base of its
parts (the VisionStateMachine, RecipeManagement, ResultManagement, SafetyStateManagement
and SystemState mixins MachineVisionServer in cell/service/machinevision.py inherits), the
method error, and the conversions of the specification's id structures."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from asyncua import Node, Server, ua
from asyncua.server.event_generator import EventGenerator

from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import Command, JobRequest, RecipeRequest, VisionState
from cell.core.eventbus import Subscription
from cell.core.events import Event, Origin, Role
from cell.recipes import RecipeBook, RecipeError, check_recipe_id
from cell.service.mv_config import MachineVisionConfig
from cell.service.mv_results import ResultMaker
from cell.service.results import ResultStore, VisionResult
from cell.service.ua_values import node_id

if TYPE_CHECKING:
    from cell.service.mv_recipes import RecipeTransfer

# One logger for the whole Machine Vision server, its parts included: cell.service.machinevision.
log = logging.getLogger("cell.service.machinevision")

CHILD_REFS = {
    node_id(i) for i in (ua.ObjectIds.HasComponent, ua.ObjectIds.HasProperty, ua.ObjectIds.HasOrderedComponent)
}


class MethodError(Exception):
    """A method call ends with this status code (the reason is logged)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class MachineVisionParts:
    """The attributes every part of MachineVisionServer uses (set by MachineVisionServer.__init__),
    and, for the type checker only, the methods one part calls on another or on the server."""

    server: Server
    service: LineServiceAPI
    config: CellConfig
    mv: MachineVisionConfig
    results: ResultStore
    recipes: RecipeBook
    _maker: ResultMaker
    node: Node | None  # the VisionSystem object
    _n: dict[str, Node]
    _states: dict[str, tuple[ua.NodeId, int]]  # state BrowseName -> (type's node, number)
    _transitions: dict[str, tuple[ua.NodeId, int]]
    _place: tuple[str, str]
    _queue: deque[Event | VisionResult]
    _wake: asyncio.Event | None
    _task: asyncio.Task[None] | None
    _subscription: Subscription | None
    _last_command: Command | None
    _failing: set[str]
    _tries: int
    _written: dict[str, Any]
    _handles: dict[int, list[str]]
    _transfers: dict[ua.NodeId, RecipeTransfer]
    _recipe_nodes: dict[str, Node]  # recipe id -> its object in Recipes (files and transfers)
    _lookups_waiting: int  # GetResultById calls waiting for the history store
    _safety: tuple[bool, str]
    _ns: dict[str, int]
    _generators: dict[str, EventGenerator]
    _background: set[asyncio.Task[None]]

    if TYPE_CHECKING:  # defined by MachineVisionServer and its parts

        def _wrap(
            self, name: str, handler: Callable[..., Awaitable[list[ua.Variant]]], role: Role
        ) -> Callable[..., Any]: ...

        @staticmethod
        def _origin() -> Origin: ...

        def _command(self, command: Command, request: JobRequest | RecipeRequest | None = None) -> str | None: ...

        @staticmethod
        def _ok() -> list[ua.Variant]: ...

        async def _read_only(self, nodes: set[ua.NodeId] | None = None) -> None: ...

        async def _enter(self, state: VisionState, initial: bool = False) -> None: ...

        async def _refresh_recipe_folder(self) -> None: ...

        def _new_handle(self, ids: list[str]) -> int: ...


# ---- conversions ------------------------------------------------------------------------
def spec_id(value: Any) -> str:
    """The Id of one of the specification's *IdDataType structures (or a plain string)."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return str(getattr(value, "Id", "") or "")


def valid_recipe_id(recipe_id: str) -> bool:
    try:
        check_recipe_id(recipe_id)
    except RecipeError:
        return False
    return True


def bad_recipe_id(what: str) -> None:
    raise MethodError(ua.StatusCodes.BadInvalidArgument, f"{what}: not an allowed recipe id")
