"""OPC UA Part 10 on the Program object, as a generic client reads it (issue 29): asyncua's
client against a real `softplc run` on a free loopback port. States by Part 10's table
(Start only from Ready, Resume only from Suspended, Reset only from Halted), Executable per
state, LastTransition, ProgramTransitionEventType events on the Server object, the type's
method ids, calls on a wrong object, OutputArguments, optional properties not null."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from asyncua import Node, ua

from softplc.opcua.ids import numeric_id, string_id
from tests.opcua.conftest import Plc
from tests.opcua.test_server import TIMEOUT_S, Collector, _client, _current, _node, _until

NS_URI = "urn:softplc"


async def _executable(program: Node) -> dict[str, bool]:
    out = {}
    for name in ("Start", "Suspend", "Resume", "Halt", "Reset"):
        node = await program.get_child(f"0:{name}")
        value = await node.read_attribute(ua.AttributeIds.Executable)
        out[name] = bool(value.Value is not None and value.Value.Value)
    return out


async def _transitions(seen: Collector) -> list[str]:
    return [e.Transition.Text for e in seen.events if getattr(e, "Transition", None)]


def test_part10_state_machine_methods_and_events(shared_plc: Plc) -> None:
    async def body() -> None:
        async with _client(shared_plc, shared_plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            program = _node(client, ns, "PLC.Program")
            seen = Collector()
            sub = await client.create_subscription(20, seen)
            await sub.subscribe_events(client.get_node(ua.ObjectIds.Server),
                                       client.get_node(ua.ObjectIds.ProgramTransitionEventType))
            await _until(lambda: _current(client, ns, "Running"))
            assert await _executable(program) == {"Start": False, "Suspend": True,
                                                  "Resume": False, "Halt": True, "Reset": False}

            async def call(method: Any, *args: Any) -> list[Any]:
                result: list[Any] = await program.call_method(method, *args)
                return result

            # a wrong object: the Suspend method id on PLC is refused and changes nothing
            plc = _node(client, ns, "PLC")
            with pytest.raises(ua.uaerrors.BadMethodInvalid):
                await plc.call_method(string_id("PLC.Program.Suspend", ns))
            assert await _node(client, ns, "PLC.Status.State").read_value() == "RUNNING"
            assert (await call("0:Suspend"))[1] == "STOPPED"
            await _until(lambda: _current(client, ns, "Suspended"))
            # Start after Suspend would throw the marking away: refused, Resume named
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await call("0:Start")
            last = await _node(client, ns, "PLC.Program.LastResult").read_value()
            assert "Resume" in last
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await call("0:Reset")  # Part 10: Reset only from Halted
            assert await _executable(program) == {"Start": False, "Suspend": False,
                                                  "Resume": True, "Halt": True, "Reset": False}
            # the type's method id reaches the instance
            assert (await call(numeric_id(ua.ObjectIds.ProgramStateMachineType_Resume)))[1] \
                == "RUNNING"
            await _until(lambda: _current(client, ns, "Running"))  # each step seen: its event
            assert (await call("0:Halt"))[1] == "KILLED"
            await _until(lambda: _current(client, ns, "Halted"))
            assert (await call("0:Reset"))[1] == "STOPPED"
            await _until(lambda: _current(client, ns, "Ready"))
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await call("0:Resume")  # nothing to resume in Ready
            last_transition = await program.get_child("0:LastTransition")
            assert (await last_transition.read_value()).Text == "HaltedToReady"
            assert await (await last_transition.get_child("0:Number")).read_value() == 1
            assert await (await last_transition.get_child("0:TransitionTime")).read_value()
            assert (await call("0:Start"))[1] == "RUNNING"
            expected = ["RunningToSuspended", "SuspendedToRunning", "RunningToHalted",
                        "HaltedToReady", "ReadyToRunning"]
            await _until(lambda: _has_all(seen, expected), TIMEOUT_S)
            assert [t for t in await _transitions(seen) if t in expected] == expected
            await sub.delete()

    asyncio.run(body())


async def _has_all(seen: Collector, names: list[str]) -> bool:
    return set(names) <= set(await _transitions(seen))


def test_program_object_declares_what_part10_makes_optional(shared_plc: Plc) -> None:
    async def body() -> None:
        async with _client(shared_plc) as client:
            ns = await client.get_namespace_index(NS_URI)
            program = _node(client, ns, "PLC.Program")
            for name in ("Start", "Suspend", "Resume", "Halt", "Reset"):
                method = await program.get_child(f"0:{name}")
                outputs = await (await method.get_child("0:OutputArguments")).read_value()
                assert [a.Name for a in outputs] == ["Message", "State"]
            assert await (await program.get_child("0:Deletable")).read_value() is False
            assert await (await program.get_child("0:AutoDelete")).read_value() is False
            assert await (await program.get_child("0:RecycleCount")).read_value() == 0
            states = await (await program.get_child("0:AvailableStates")).read_value()
            assert len(states) == 4
            with pytest.raises(ua.uaerrors.BadNoMatch):
                await program.get_child("0:ProgramDiagnostic")  # absent, not null
            notifier = await program.read_event_notifier()
            assert ua.EventNotifier.SubscribeToEvents in notifier
            refs = await client.get_node(ua.ObjectIds.Server).get_referenced_nodes(
                ua.ObjectIds.HasNotifier)
            assert _node(client, ns, "PLC").nodeid in [r.nodeid for r in refs]

    asyncio.run(body())


def test_events_reach_the_server_object_and_transitions_a_subscription_on_plc(
        transport_plc: Plc) -> None:
    """One Suspend, two subscriptions, each with its own filter and handler: softplc's own
    events reach a subscription on the Server object; PLC -HasNotifier-> PLC.Program (Part 3):
    a subscription on PLC receives what its Program raises, SourceNode still the Program
    (issue 39 item 8; it reached Server only). One PLC for both: a start costs 7-15 s."""
    async def body() -> None:
        async with _client(transport_plc, transport_plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            program = _node(client, ns, "PLC.Program")
            on_server, on_plc = Collector(), Collector()
            server_sub = await client.create_subscription(20, on_server)
            etype = await client.get_node(ua.ObjectIds.BaseEventType).get_child(
                f"{ns}:SoftplcEventType")
            await server_sub.subscribe_events(client.get_node(ua.ObjectIds.Server), etype)
            plc_sub = await client.create_subscription(20, on_plc)
            await plc_sub.subscribe_events(_node(client, ns, "PLC"), client.get_node(
                ua.ObjectIds.ProgramTransitionEventType))
            await _until(lambda: _current(client, ns, "Running"))
            await program.call_method("0:Suspend")
            await _until(lambda: _named(on_server, "state"))
            await _until(lambda: _has_all(on_plc, ["RunningToSuspended"]))
            event = next(e for e in on_plc.events if e.Transition.Text == "RunningToSuspended")
            assert event.SourceNode == program.nodeid
            await server_sub.delete()
            await plc_sub.delete()

    asyncio.run(body())


async def _named(seen: Collector, name: str) -> bool:
    return name in seen.names()


def test_a_call_naming_no_method_or_no_object_gets_part4_codes(shared_plc: Plc) -> None:
    """Part 4 (Call): a MethodId that names no Method is BadMethodInvalid (asyncua answered
    BadNodeIdInvalid), an ObjectId that names no node BadNodeIdUnknown; nothing changes."""
    async def body() -> None:
        async with _client(shared_plc, shared_plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            program, plc = _node(client, ns, "PLC.Program"), _node(client, ns, "PLC")
            with pytest.raises(ua.uaerrors.BadMethodInvalid):
                await program.call_method(string_id("PLC.Program.Explode", ns))
            with pytest.raises(ua.uaerrors.BadMethodInvalid):  # a variable, not a method
                await plc.call_method(string_id("PLC.Status.State", ns))
            with pytest.raises(ua.uaerrors.BadNodeIdUnknown):
                await _node(client, ns, "PLC.Nowhere").call_method(
                    string_id("PLC.Program.Suspend", ns))
            assert await _node(client, ns, "PLC.Status.State").read_value() == "RUNNING"

    asyncio.run(body())
