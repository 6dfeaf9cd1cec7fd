"""Data as a SCADA client reads it (issue 29, item 3), and Republish as Part 4 says (item 4),
against a real `softplc run` (scan + OPC UA process) with asyncua's client: timestamps from
the snapshot, quality that follows freshness (scan process frozen with SIGSTOP), softplc's own
identity, per-session access levels, exact type checks on writes, BadNodeIdUnknown."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import Client, ua

import softplc
from softplc.opcua.ids import string_id
from tests.opcua.conftest import Plc, patient_client, start_plc, stop_plc
from tests.opcua.pids import api_status
from tests.support import free_port

NS_URI = "urn:softplc"


@pytest.fixture(scope="module")
def plc_with_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Plc, int]]:
    """One PLC for the module (a start costs 7-15 s): each test leaves it as it found it
    (the frozen scan process is thawed and Good again; a write to a counter changes no
    other test's facts)."""
    api_port = free_port()
    plc = start_plc("programs/transport.yaml", tmp_path_factory.mktemp("scada"), "--api",
                    f"127.0.0.1:{api_port}")
    try:
        yield plc, api_port
    finally:
        stop_plc(plc.proc)


def _client(plc: Plc, token: str | None = None) -> Client:
    client = patient_client(plc.url)
    if token is not None:
        client.set_user("operator")
        client.set_password(token)
    return client


async def _read(client: Client, nodeid: ua.NodeId, wanted: ua.TimestampsToReturn,
                attribute: ua.AttributeIds = ua.AttributeIds.Value) -> ua.DataValue:
    params = ua.ReadParameters(TimestampsToReturn=wanted, NodesToRead=[
        ua.ReadValueId(NodeId=nodeid, AttributeId=attribute)])
    (value,) = await client.uaclient.read(params)
    return value


async def _until_status(client: Client, nodeid: ua.NodeId, code: int,
                        timeout_s: float = 10.0) -> ua.DataValue:
    deadline = time.monotonic() + timeout_s
    while True:
        value = await _read(client, nodeid, ua.TimestampsToReturn.Both)
        if value.StatusCode is not None and value.StatusCode.value == code:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{nodeid} never had status {code:#x}; last {value}")
        await asyncio.sleep(0.05)


def test_timestamps_and_quality_follow_the_snapshot(plc_with_api: tuple[Plc, int]) -> None:
    plc, api_port = plc_with_api
    scan_pid = 0

    async def body() -> None:
        nonlocal scan_pid
        async with _client(plc) as client:
            ns = await client.get_namespace_index(NS_URI)
            count = string_id("PLC.Status.ScanCount", ns)
            symbol = string_id("PLC.Symbols.s1_i", ns)
            for nodeid in (count, symbol):
                value = await _until_status(client, nodeid, ua.StatusCodes.Good)
                now = datetime.now(UTC)
                assert value.SourceTimestamp is not None and value.ServerTimestamp is not None
                assert value.SourceTimestamp <= value.ServerTimestamp + timedelta(seconds=0.05)
                if nodeid == count:  # changes every scan: stamped by a recent publish
                    assert now - value.SourceTimestamp < timedelta(seconds=2)
            bare = await _read(client, count, ua.TimestampsToReturn.Neither)
            assert bare.SourceTimestamp is None and bare.ServerTimestamp is None
            source_only = await _read(client, count, ua.TimestampsToReturn.Source)
            assert source_only.SourceTimestamp and source_only.ServerTimestamp is None
            scan_pid = int(str(api_status(api_port, plc.token)["scan_pid"]))
            frozen_at = datetime.now(UTC)
            os.kill(scan_pid, signal.SIGSTOP)
            try:
                stale = await _until_status(client, count, ua.StatusCodes.UncertainLastUsableValue,
                                            timeout_s=3.0)
                assert stale.SourceTimestamp is not None and stale.SourceTimestamp <= frozen_at
                await _until_status(client, symbol, ua.StatusCodes.UncertainLastUsableValue,
                                    timeout_s=3.0)
            finally:
                os.kill(scan_pid, signal.SIGCONT)
            await _until_status(client, count, ua.StatusCodes.Good, timeout_s=30.0)

    try:
        asyncio.run(body())
    finally:
        if scan_pid:
            os.kill(scan_pid, signal.SIGCONT)


def test_identity_access_levels_and_writes(plc_with_api: tuple[Plc, int]) -> None:
    plc, _ = plc_with_api

    async def body() -> None:
        async with _client(plc) as anonymous, _client(plc, plc.token) as operator:
            ns = await anonymous.get_namespace_index(NS_URI)
            uri = (await anonymous.get_node(ua.ObjectIds.Server_ServerArray).read_value())[0]
            assert uri.startswith("urn:softplc:") and "freeopcua" not in uri
            (endpoint, *_) = await anonymous.get_endpoints()
            assert endpoint.Server.ApplicationUri == uri
            assert endpoint.Server.ProductUri == NS_URI
            build = await anonymous.get_node(
                ua.ObjectIds.Server_ServerStatus_BuildInfo).read_value()
            assert (build.ProductName, build.SoftwareVersion, build.ManufacturerName) == (
                "softplc", softplc.__version__, "softplc")
            hold, start = string_id("PLC.Symbols.hold", ns), string_id("PLC.Program.Start", ns)
            write = 1 << int(ua.AccessLevel.CurrentWrite)
            for client, may in ((anonymous, False), (operator, True)):
                level = await _read(client, hold, ua.TimestampsToReturn.Neither,
                                    ua.AttributeIds.AccessLevel)
                user = await _read(client, hold, ua.TimestampsToReturn.Neither,
                                   ua.AttributeIds.UserAccessLevel)
                assert level.Value is not None and user.Value is not None
                assert level.Value.Value & write  # the node is writable
                assert bool(user.Value.Value & write) is may  # by this session?
            theirs = await _read(anonymous, start, ua.TimestampsToReturn.Neither,
                                 ua.AttributeIds.UserExecutable)
            assert theirs.Value is not None and theirs.Value.Value is False
            stopped = await _read(operator, start, ua.TimestampsToReturn.Neither,
                                  ua.AttributeIds.Executable)
            mine = await _read(operator, start, ua.TimestampsToReturn.Neither,
                               ua.AttributeIds.UserExecutable)
            assert mine.Value is not None and stopped.Value is not None
            assert mine.Value.Value is stopped.Value.Value  # Start: not while Running
            await _writes(operator, ns)

    asyncio.run(body())


async def _writes(client: Client, ns: int) -> None:
    """Exactly the node's DataType: Int32 to UInt16 refused like UInt16 to Boolean."""
    counter = client.get_node(string_id("PLC.Symbols.parts_delivered", ns))
    hold = client.get_node(string_id("PLC.Symbols.hold", ns))
    with pytest.raises(ua.uaerrors.BadTypeMismatch):
        await counter.write_value(ua.Variant(7, ua.VariantType.Int32))
    with pytest.raises(ua.uaerrors.BadTypeMismatch):
        await hold.write_value(ua.Variant(1, ua.VariantType.UInt16))
    await counter.write_value(ua.Variant(7, ua.VariantType.UInt16))
    with pytest.raises(ua.uaerrors.BadNodeIdUnknown):
        await client.get_node(string_id("PLC.Symbols.no_such", ns)).write_value(
            ua.Variant(True, ua.VariantType.Boolean))


def test_republish_answers_as_the_spec_says(plc_with_api: tuple[Plc, int]) -> None:
    plc, _ = plc_with_api

    async def body() -> None:
        async with _client(plc) as client:
            protocol = client.uaclient.protocol
            assert protocol is not None
            with pytest.raises(ua.uaerrors.BadSubscriptionIdInvalid):
                await protocol.send_request(ua.RepublishRequest(Parameters=ua.RepublishParameters(
                    SubscriptionId=987654, RetransmitSequenceNumber=1)))
            subscription = await client.create_subscription(100, None)
            with pytest.raises(ua.uaerrors.BadMessageNotAvailable):
                await protocol.send_request(ua.RepublishRequest(Parameters=ua.RepublishParameters(
                    SubscriptionId=subscription.subscription_id,
                    RetransmitSequenceNumber=4000)))

    asyncio.run(body())
