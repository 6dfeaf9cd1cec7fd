"""The symbol routes: `GET /api/v1/symbols`, `GET` and `PUT /api/v1/symbols/{name}`.

Owns: a symbol's view (name, address, type, direction, value: from the latest snapshot, or
the board's value when no snapshot can be read, typed by core/present.py; `raw`, the bits
unconverted), and checking a write against the symbol's direction, `hmi_writable` and type
before it is queued for the next scan (`write_raw`, which forces use too).
Does not know: the image's layout (core/image.py parses addresses), the channel's pipes.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import Any

from aiohttp import web

from softplc.api.openapi import API_PREFIX
from softplc.api.problems import ApiProblem, json_body
from softplc.api.service import ApiService
from softplc.core.image import AddressError, parse_address, split_registers
from softplc.core.present import Shown, ValueRefused, accepted, shown
from softplc.core.snapshot import ChannelFull, HmiWrite
from softplc.security.writes import symbol_refusal


def register(app: web.Application, api: ApiService) -> None:
    """Add the symbol routes to `app` (server.py's build_app calls this once)."""
    routes = _Routes(api)
    app.router.add_get(f"{API_PREFIX}/symbols", routes.symbols)
    app.router.add_get(f"{API_PREFIX}/symbols/{{name}}", routes.symbol)
    app.router.add_put(f"{API_PREFIX}/symbols/{{name}}", routes.write)


def view(name: str, entry: Mapping[str, Any], image: Any) -> dict[str, Any]:
    """A symbol's answer: the board's entry, its value read from `image` when there is one,
    as its type reads (core/present.py): a negative int, a real as a decimal number."""
    answer = {"name": name, "address": entry.get("address"), "type": entry.get("type"),
              "direction": entry.get("direction"), "value": value_of_entry(entry, image),
              "raw": raw_of_entry(entry, image)}
    if "scale" in entry:  # the value is in engineering units (docs/programs.md, scaling)
        answer["unit"], answer["scale"] = entry.get("unit", ""), entry["scale"]
    return answer


def value_of_entry(entry: Mapping[str, Any], image: Any) -> Shown:
    """The typed value of a board entry: from `image` (the latest snapshot) when it can be
    read there, else the board's own (already typed) value."""
    if image is not None:
        with contextlib.suppress(AddressError, TypeError, KeyError, IndexError):
            return shown(entry.get("type"), image.get(parse_address(str(entry["address"]))),
                         entry.get("scale"))
    value: Shown = entry.get("value", 0)
    return bool(value) if entry.get("type") == "bool" else value


def raw_of_entry(entry: Mapping[str, Any], image: Any) -> int | None:
    """The bits the symbol's location holds (a real's pattern, a scaled symbol's raw count as
    the image stores it): from `image` when it can be read there, else the board's."""
    if image is not None:
        with contextlib.suppress(AddressError, TypeError, KeyError, IndexError):
            return int(image.get(parse_address(str(entry["address"]))))
    raw = entry.get("raw")
    return raw if type(raw) is int else None


def write_raw(name: str, entry: Mapping[str, Any] | None, body: Any) -> int:
    """The raw bits a write or a force of `{"value": v}` to `name` stores, checked against the
    symbol's type in the board `entry` (core/present.py); 422 naming the symbol, its type and
    what it takes. Without an entry (a program the board does not show yet) a bool or an
    integer goes as it is: the scan checks it against the program it runs."""
    if not isinstance(body, dict) or "value" not in body:
        raise ApiProblem(422, 'the body must be a JSON object {"value": n}')
    value = body["value"]
    if entry is None:
        if isinstance(value, bool) or type(value) is int:
            return int(value)
        raise ApiProblem(422, f"no symbol {name!r} in the loaded program")
    try:
        return accepted(entry.get("type"), value, name, entry.get("scale"))
    except ValueRefused as exc:
        raise ApiProblem(422, str(exc)) from None


class _Routes:
    def __init__(self, api: ApiService) -> None:
        self._api = api

    async def _table(self) -> dict[str, dict[str, Any]]:
        symbols = (await self._api.board_document()).get("symbols") or {}
        return {k: v for k, v in symbols.items() if isinstance(v, dict)}

    async def _lookup(self, request: web.Request) -> tuple[str, dict[str, Any]]:
        name = request.match_info["name"]
        entry = (await self._table()).get(name)
        if entry is None:
            raise ApiProblem(404, f"no symbol {name!r} in the loaded program")
        return name, entry

    async def symbols(self, request: web.Request) -> web.Response:
        table = await self._table()
        seq, image = self._api.image()
        return web.json_response({"snapshot_seq": seq, "symbols": {
            name: view(name, entry, image) for name, entry in table.items()}})

    async def symbol(self, request: web.Request) -> web.Response:
        name, entry = await self._lookup(request)
        return web.json_response(view(name, entry, self._api.image()[1]))

    async def write(self, request: web.Request) -> web.Response:
        name, entry = await self._lookup(request)
        refusal = symbol_refusal(name, entry)
        if refusal is not None:
            raise ApiProblem(403, refusal)
        raw = write_raw(name, entry, await json_body(request))
        try:
            address = parse_address(str(entry.get("address")))
        except AddressError as exc:
            raise ApiProblem(409, f"symbol {name} has no usable address: {exc}") from None
        try:  # a double or long word goes whole, as its 2 or 4 registers (one HMI write)
            registers = (raw,) if address.is_bit else tuple(split_registers(raw, address.width))
            self._api.channel.send_hmi_write(HmiWrite(address, registers))
        except ChannelFull as exc:
            raise ApiProblem(503, str(exc), headers={"Retry-After": "1"}) from None
        return web.json_response({"name": name, "address": str(address),
                                  "value": shown(entry.get("type"), raw, entry.get("scale")),
                                  "queued": True},
                                 status=202)
