"""The plant models by name, for the CLI, the simulator and the benchmarks.

Owns: the name -> constructor table and make_plant.
Does not know: any plant's physics, drivers, clocks.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from softplc.devices.plants.base import Plant
from softplc.devices.plants.drilling import DrillingPlant
from softplc.devices.plants.tank import TankPlant
from softplc.devices.plants.transport import TransportPlant

PLANTS: dict[str, Callable[..., Plant]] = {
    "transport": TransportPlant,
    "drilling": DrillingPlant,
    "tank": TankPlant,
}


def make_plant(name: str, seed: int = 0, **tunables: Any) -> Plant:
    """A fresh plant; tunables are the keyword fields of that plant's config dataclass."""
    try:
        factory = PLANTS[name]
    except KeyError:
        known = ", ".join(sorted(PLANTS))
        raise ValueError(f"unknown plant {name!r} (known plants: {known})") from None
    return factory(seed=seed, **tunables)
