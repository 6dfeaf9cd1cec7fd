"""What a client may write into the image: one rule for every door that writes (issue 38).

Owns: the symbol rule, which holds at every door whatever its role or policy: an input belongs
to its drivers and a symbol its program declares `hmi_writable: false` is the program's alone
(the HTTP API, OPC UA, Sparkplug B and Modbus in every write policy refuse it); the Modbus
write policy (`--modbus-writes`: open, symbols, none; docs/modbus.md "Write policy"), which
OPC UA follows too; the image locations each policy opens or keeps closed, from the board's
symbol table. Who may write at all (the role) is `decide.py`'s.
Does not know: a door, the board's freshness (the doors check that the board describes the
running program before they use its table).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final, Literal, get_args

from softplc.core.image import Address, AddressError, parse_address

# "open": OpenPLC's behaviour, every coil and holding register (outputs and memory) but the
# locations of symbols declared `hmi_writable: false`; "symbols": only the running program's
# out/memory symbols that may be written; "none": read-only. Inputs are never writable.
WritePolicy = Literal["open", "symbols", "none"]
WRITE_POLICIES: Final[tuple[str, ...]] = get_args(WritePolicy)


def symbol_refusal(name: str, entry: Mapping[str, Any]) -> str | None:
    """Why no client may write symbol `name` (its board entry), or None: the rule every door
    applies before its own (policy, role, type)."""
    if entry.get("direction") == "in":
        return f"symbol {name} ({entry.get('address')}) is an input: inputs belong to the drivers"
    if entry.get("hmi_writable", True) is not True:
        return f"symbol {name} is declared hmi_writable: false"
    return None


def policy_refusal(name: str, entry: Mapping[str, Any], policy: str) -> str | None:
    """Why a door that follows the Modbus write policy (Modbus, OPC UA) refuses a write of
    symbol `name`, or None."""
    if policy == "none":
        return f"symbol {name}: the write policy is none (--modbus-writes none: read-only)"
    return symbol_refusal(name, entry)


def locations(symbols: Mapping[str, Any], *, writable: bool) -> frozenset[Address]:
    """The image locations of the board's symbols that a client may write (writable=True: the
    policy "symbols") or may not (writable=False: closed also under "open"); inputs are left
    out (they are in read-only tables), as are entries without a usable address."""
    found: set[Address] = set()
    for name, entry in symbols.items():
        if not isinstance(entry, Mapping) or entry.get("direction") == "in":
            continue
        if (symbol_refusal(str(name), entry) is None) is not writable:
            continue
        try:
            found.add(parse_address(str(entry.get("address"))))
        except AddressError:
            continue
    return frozenset(found)
