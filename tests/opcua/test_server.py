"""asyncua's client against a real `softplc run` (scan + communication processes) serving
OPC UA on a free loopback port: browse, read, write (refused and allowed), subscriptions to
data changes and events, every Program method, an online download of drilling."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua

from tests.opcua.conftest import ROOT, Plc, patient_client

NS_URI = "urn:softplc"
TIMEOUT_S = 30.0


async def _until(check: Callable[[], Awaitable[Any]], timeout_s: float = TIMEOUT_S) -> Any:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while True:
        value = await check()
        if value:
            return value
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.05)


def _client(plc: Plc, token: str | None = None) -> Client:
    # OPC UA is served last when the CPUs are busy (niceness 10, docs/design.md section 7):
    # beside 4 busy loops, rebuilding the address space for a downloaded program took the
    # server longer than 10 s, and asyncua's watchdog dropped the session. The client waits
    # as an operator's would; what is checked is the answers.
    client = patient_client(plc.url)
    if token is not None:
        client.set_user("operator")
        client.set_password(token)
    return client


def _node(client: Client, ns: int, text: str) -> Node:
    return client.get_node(ua.NodeId(text, ns))


class Collector:
    """Subscription handler: every data change and event, in order."""

    def __init__(self) -> None:
        self.changes: list[tuple[str, Any]] = []
        self.events: list[Any] = []

    def datachange_notification(self, node: Node, value: Any, data: Any) -> None:
        self.changes.append((str(node.nodeid.Identifier), value))

    def event_notification(self, event: Any) -> None:
        self.events.append(event)

    def names(self) -> list[str]:
        return [str(getattr(e, "EventName", "")) for e in self.events]


def test_browse_read_and_anonymous_refusals(shared_plc: Plc) -> None:
    async def body() -> None:
        async with _client(shared_plc) as client:
            ns = await client.get_namespace_index(NS_URI)
            symbols = await _node(client, ns, "PLC.Symbols").get_children()
            names = {(await n.read_browse_name()).Name: n for n in symbols}
            assert set(names) == {"s1_i", "s1_o", "s2_i", "s2_o", "m1", "m2",
                                  "parts_delivered", "hold"}
            assert await names["s1_i"].read_data_type_as_variant_type() == ua.VariantType.Boolean
            assert (await names["parts_delivered"].read_data_type_as_variant_type()
                    == ua.VariantType.UInt16)
            level = await names["s1_i"].get_access_level()
            assert ua.AccessLevel.CurrentWrite not in level  # inputs are read-only
            assert ua.AccessLevel.CurrentWrite in await names["hold"].get_access_level()
            description = (await names["s1_i"].read_description()).Text
            assert "%IX0.0" in description
            count = _node(client, ns, "PLC.Status.ScanCount")
            first = await count.read_value()
            await _until(lambda: _bigger(count, first + 10))
            assert await _node(client, ns, "PLC.Status.State").read_value() == "RUNNING"
            program = _node(client, ns, "PLC.Program")
            state = await _node(client, ns, "PLC.Program.CurrentState").read_value()
            assert state.Text == "Running"
            places = await _node(client, ns, "PLC.Marking").get_children()
            assert {(await p.read_browse_name()).Name for p in places} >= {"delivered"}
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await names["hold"].write_value(ua.Variant(True, ua.VariantType.Boolean))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await program.call_method("0:Suspend")
            assert await _node(client, ns, "PLC.Status.State").read_value() == "RUNNING"

    asyncio.run(body())


async def _bigger(node: Node, than: int) -> bool:
    return int(await node.read_value()) > than


def test_wrong_token_is_refused_at_activation(shared_plc: Plc) -> None:
    async def body() -> None:
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with _client(shared_plc, "not-the-token"):
                pass

    asyncio.run(body())


def test_operator_writes_journaled_and_refused_with_status_codes(shared_plc: Plc) -> None:
    async def body() -> None:
        async with _client(shared_plc, shared_plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            hold = _node(client, ns, "PLC.Symbols.hold")
            await hold.write_value(ua.Variant(True, ua.VariantType.Boolean))
            await _until(hold.read_value)  # journaled, applied by a scan, published back
            with pytest.raises(ua.uaerrors.BadNotWritable):  # an input belongs to the drivers
                await _node(client, ns, "PLC.Symbols.s1_i").write_value(
                    ua.Variant(True, ua.VariantType.Boolean))
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await hold.write_value(ua.Variant(7, ua.VariantType.Int32))
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await _node(client, ns, "PLC.Symbols.parts_delivered").write_value(
                    ua.Variant(70000, ua.VariantType.UInt32))
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):  # status is read-only
                await _node(client, ns, "PLC.Status.ScanCount").write_value(
                    ua.Variant(1, ua.VariantType.UInt64))
            await hold.write_value(ua.Variant(False, ua.VariantType.Boolean))
            await _until(lambda: _is_false(hold))

    asyncio.run(body())


async def _is_false(node: Node) -> bool:
    return await node.read_value() is False


def test_subscriptions_every_method_and_online_download(transport_plc: Plc) -> None:
    drilling = (ROOT / "programs" / "drilling.yaml").read_text()

    async def body() -> None:
        async with _client(transport_plc, transport_plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            program = _node(client, ns, "PLC.Program")
            state = _node(client, ns, "PLC.Status.State")
            seen = Collector()
            sub = await client.create_subscription(20, seen)
            await sub.subscribe_data_change(
                [_node(client, ns, "PLC.Symbols.s1_i"), state])
            await sub.subscribe_events(_node(client, ns, "PLC"),
                                       await _event_type(client, ns))
            # the transport plant puts a part in front of s1_i after about a second
            await _until(lambda: _has(seen.changes, ("PLC.Symbols.s1_i", True)))

            async def call(method: str, *args: ua.Variant) -> list[Any]:
                result: list[Any] = await program.call_method(method, *args)
                return result

            assert (await call("0:Suspend"))[1] == "STOPPED"
            await _until(lambda: _current(client, ns, "Suspended"))
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await call("0:Suspend")  # refused by the lifecycle table: STOPPED already
            assert "refused" in await _node(client, ns, "PLC.Program.LastResult").read_value()
            assert (await call("0:Resume"))[1] == "RUNNING"
            assert (await call("0:Halt"))[1] == "KILLED"
            await _until(lambda: _current(client, ns, "Halted"))
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await call("0:Start")
            assert (await call("0:Reset"))[1] == "STOPPED"
            await _until(lambda: _current(client, ns, "Ready"))
            assert (await call("0:Start"))[1] == "RUNNING"
            await _until(lambda: _has(seen.changes, ("PLC.Status.State", "KILLED")))
            await _until(lambda: _contains(seen.names(), "state"))
            # a bad program: refused with the compiler's problems, nothing changes
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await call(f"{ns}:Download", ua.Variant("places: [", ua.VariantType.String),
                           ua.Variant(True, ua.VariantType.Boolean),
                           ua.Variant("bad.yaml", ua.VariantType.String))
            problems = await _node(client, ns, "PLC.Program.LastProblems").read_value()
            assert problems and all("bad.yaml" in p for p in problems)
            with pytest.raises(ua.uaerrors.BadArgumentsMissing):
                await call(f"{ns}:Download")
            reply = await call(f"{ns}:Download", ua.Variant(drilling, ua.VariantType.String),
                               ua.Variant(True, ua.VariantType.Boolean),
                               ua.Variant("drilling.yaml", ua.VariantType.String))
            assert reply[1] == "RUNNING"
            await _until(lambda: _contains(seen.names(), "download"))
            download = next(e for e in seen.events if e.EventName == "download")
            assert "drilling" in download.Message.Text
            await _until(lambda: _has_symbol(client, ns, "drill_top"))
            assert await _node(client, ns, "PLC.Status.State").read_value() == "RUNNING"
            await sub.delete()

    asyncio.run(body())


async def _event_type(client: Client, ns: int) -> Node:
    types = client.get_node(ua.ObjectIds.BaseEventType)
    return await types.get_child(f"{ns}:SoftplcEventType")


async def _has(changes: list[tuple[str, Any]], item: tuple[str, Any]) -> bool:
    return item in changes


async def _contains(names: list[str], name: str) -> bool:
    return name in names


async def _current(client: Client, ns: int, text: str) -> bool:
    value = await _node(client, ns, "PLC.Program.CurrentState").read_value()
    return bool(value.Text == text)


async def _has_symbol(client: Client, ns: int, name: str) -> bool:
    try:
        await _node(client, ns, f"PLC.Symbols.{name}").read_value()
    except ua.UaStatusCodeError:
        return False
    return True


def test_state_dir_token_is_private(shared_plc: Plc) -> None:
    mode = Path(shared_plc.state_dir / "api_token").stat().st_mode & 0o777
    assert mode == 0o600
