"""The registry of part classes: the names every consumer counts and shows by.

A part class is a name the vision gives a located part (`bolt`, `nut`, a taught type's name)
and the words the interfaces derive from it: the counter's name on OPC UA (`PickedBolts`), in
Sparkplug (`Counters/Picked Bolts`) and on /metrics (`picked_bolts`). Nothing downstream of the
vision writes a class name into its code: counters, OPC UA, Sparkplug, Prometheus, the history's
queries and the screen iterate over the registry, so a class added to it (a taught part type) is
counted and shown everywhere without another line.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")  # a class name: safe in a path, a topic and a label


class UnknownPartClass(KeyError):
    """A class name the registry does not know."""


@dataclass(frozen=True)
class PartClass:
    """One kind of part the cell tells apart and counts."""

    name: str  # lower case: bolt, nut, bracket-l (what the vision says, the history's `class`)
    plural: str  # for the counters' words: bolts, nuts

    def __post_init__(self) -> None:
        for what, value in (("name", self.name), ("plural", self.plural)):
            if not NAME_PATTERN.match(value):
                raise ValueError(
                    f"part class {what} {value!r}: 1-32 characters, lower-case letters, digits, - and _, "
                    "starting with a letter"
                )

    @property
    def words(self) -> list[str]:
        return [w for w in re.split(r"[-_]", self.plural) if w]

    @property
    def counter_key(self) -> str:
        """The counter's key in records and on /metrics: picked_bolts."""
        return "picked_" + "_".join(self.words)

    @property
    def opcua_name(self) -> str:
        """The counter's OPC UA BrowseName: PickedBolts."""
        return "Picked" + "".join(w.capitalize() for w in self.words)

    @property
    def sparkplug_name(self) -> str:
        """The counter's Sparkplug metric name: Counters/Picked Bolts."""
        return "Counters/Picked " + " ".join(w.capitalize() for w in self.words)


class PartRegistry:
    """The part classes in a fixed order (the order counters are listed and shown in)."""

    def __init__(self, classes: Iterable[PartClass]):
        self._classes: dict[str, PartClass] = {}
        for c in classes:
            if c.name in self._classes:
                raise ValueError(f"part class {c.name!r} registered twice")
            self._classes[c.name] = c
        keys = [c.counter_key for c in self._classes.values()]
        if len(set(keys)) != len(keys):
            raise ValueError(f"two part classes share a counter name: {sorted(keys)}")

    def __iter__(self) -> Iterator[PartClass]:
        return iter(self._classes.values())

    def __len__(self) -> int:
        return len(self._classes)

    def __contains__(self, name: object) -> bool:
        return name in self._classes

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._classes)

    def get(self, name: str) -> PartClass:
        try:
            return self._classes[name]
        except KeyError:
            raise UnknownPartClass(f"unknown part class {name!r}; known: {', '.join(self._classes)}") from None

    def with_classes(self, classes: Iterable[PartClass]) -> PartRegistry:
        """This registry and `classes` after it (a recipe's taught types), each name once."""
        extra = [c for c in classes if c.name not in self._classes]
        return PartRegistry([*self, *extra])


BOLT = PartClass("bolt", "bolts")
NUT = PartClass("nut", "nuts")
BUILT_IN_PARTS = PartRegistry((BOLT, NUT))
"""The classes the built-in vision tells apart (cell.vision.classify)."""
