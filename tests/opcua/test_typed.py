"""Typed symbols over OPC UA (issue 30): each symbol's DataType from its type, a scaled symbol
an AnalogItemType in engineering units with EngineeringUnits and EURange, writes converted
back to raw counts (checked at the Modbus slave's registers, which show the image's raw
bits), refusals that change nothing, a NaN real. A real `softplc run` on loopback with
asyncua's client; the `kind: opcua` driver moving typed values against the same PLC."""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from asyncua import Client, ua
from pymodbus.client import ModbusTcpClient

from softplc.core.datatypes import SymType
from softplc.core.image import ProcessImage
from softplc.devices.driver import Health
from softplc.opcua.driver import OpcUaIoDriver
from softplc.opcua.ids import numeric_id, string_id
from softplc.opcua.typed import remote_raw, remote_variant
from softplc.program.io_image import parse_io_image
from tests.opcua.conftest import Plc, patient_client, start_plc, stop_plc
from tests.support import free_port

IO = """\
symbols:
  hold:   {address: "%MX0.0", type: bool}
  small:  {address: "%MW0", type: int}
  temp:   {address: "%MD0", type: real}
  count:  {address: "%MD1", type: dint}
  nan_r:  {address: "%MD2", type: real, finite: false}  # Modbus may write NaN bits here
  big:    {address: "%MD3", type: udint}
  level:  {address: "%ML0", type: lreal}
  pct:    {address: "%MW1", type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: "%"}}
  temp_c: {address: "%MW2", type: int,
           scale: {raw: [-500, 1500], eng: [-50.0, 150.0], unit: "°C", clamp: true}}
  flow:   {address: "%MW3", type: word, scale: {raw: [0, 1000], eng: [10, 0], unit: "l/min"}}
  setp:   {address: "%MW4", type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0]}}
  wide:   {address: "%MD4", type: dint}
"""
PROGRAM = """program: typed
io_image: io.yaml
places:
  idle: {tokens: 1}
  run: {}
transitions:
  begin: {from: [idle], to: [run],
          do: ["temp = 12.5", "small = -3", "count = -70000", "level = -1e300",
               "pct = 50.0", "temp_c = 21.5", "flow = 2.5"]}
"""
HOLDING_MW = 1024  # %MWn is holding register 1024 + n, %MDn 2048 + 2n (docs/modbus.md)
HOLDING_MD = 2048


class TypedPlc:
    def __init__(self, plc: Plc, modbus_port: int) -> None:
        self.plc, self.modbus_port = plc, modbus_port

    @contextlib.contextmanager
    def _modbus(self) -> Iterator[ModbusTcpClient]:
        client = ModbusTcpClient("127.0.0.1", port=self.modbus_port, timeout=3, retries=0)
        assert client.connect()  # type: ignore[no-untyped-call]
        try:
            yield client
        finally:
            client.close()  # type: ignore[no-untyped-call]

    def registers(self, address: int, count: int) -> list[int]:
        with self._modbus() as client:
            reply = client.read_holding_registers(address, count=count)
            assert not reply.isError(), reply
            return list(reply.registers)

    def write_registers(self, address: int, values: list[int]) -> None:
        with self._modbus() as client:
            assert not client.write_registers(address, values).isError()


@pytest.fixture(scope="module")
def typed_plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TypedPlc]:
    root = tmp_path_factory.mktemp("typed")
    (root / "io.yaml").write_text(IO, encoding="utf-8")
    (root / "typed.yaml").write_text(PROGRAM, encoding="utf-8")
    state = root / "state"
    state.mkdir()
    modbus_port = free_port()
    plc = start_plc(str(root / "typed.yaml"), state, "--modbus", f"127.0.0.1:{modbus_port}")
    try:
        yield TypedPlc(plc, modbus_port)
    finally:
        stop_plc(plc.proc)


def _client(plc: Plc) -> Client:
    client = patient_client(plc.url)
    client.set_user("owner")
    client.set_password(plc.token)  # the owner's key: may write
    return client


async def _until(probe: Callable[[], Any], what: str, timeout_s: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = await probe()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not in {timeout_s} s: {what}")
        await asyncio.sleep(0.05)


async def _nodes(client: Client) -> Callable[[str], Any]:
    ns = await client.get_namespace_index("urn:softplc")
    await _until(lambda: _value_is(client.get_node(string_id("PLC.Symbols.flow", ns)), 2.5),
                 "the program's writes (flow: written by the program only)")
    return lambda name: client.get_node(string_id(f"PLC.Symbols.{name}", ns))


async def _value_is(node: Any, wanted: object) -> bool:
    try:
        return bool(await node.read_value() == wanted)
    except ua.UaStatusCodeError:  # the symbols are rebuilt at the download
        return False


def test_each_type_reads_as_its_data_type(typed_plc: TypedPlc) -> None:
    async def body() -> None:
        async with _client(typed_plc.plc) as client:
            node = await _nodes(client)
            expected = {"hold": (ua.VariantType.Boolean, False),
                        "small": (ua.VariantType.Int16, -3),
                        "temp": (ua.VariantType.Float, 12.5),
                        "count": (ua.VariantType.Int32, -70000),
                        "big": (ua.VariantType.UInt32, 0),
                        "level": (ua.VariantType.Double, -1e300),
                        "pct": (ua.VariantType.Double, 50.0),  # engineering units
                        "temp_c": (ua.VariantType.Double, 21.5),
                        "flow": (ua.VariantType.Double, 2.5)}
            for name, (vtype, value) in expected.items():
                assert await node(name).read_data_type_as_variant_type() is vtype, name
                variant = (await node(name).read_data_value()).Value
                assert (variant.VariantType, variant.Value) == (vtype, value), name

    asyncio.run(body())


def test_a_scaled_symbol_is_an_analog_item(typed_plc: TypedPlc) -> None:
    async def body() -> None:
        async with _client(typed_plc.plc) as client:
            node = await _nodes(client)
            pct = node("pct")
            assert (await pct.read_type_definition()) == numeric_id(ua.ObjectIds.AnalogItemType)
            eu_range = await (await pct.get_child("0:EURange")).read_value()
            assert (eu_range.Low, eu_range.High) == (0.0, 100.0)
            units = await (await pct.get_child("0:EngineeringUnits")).read_value()
            assert units.UnitId == 0x5031  # UNECE P1, percent (Part 8: the code's bytes)
            assert units.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
            assert units.DisplayName.Text == "%"
            celsius = await (await node("temp_c").get_child("0:EngineeringUnits")).read_value()
            assert celsius.UnitId == 0x43454C and celsius.DisplayName.Text == "°C"  # CEL
            other = await (await node("flow").get_child("0:EngineeringUnits")).read_value()
            assert (other.UnitId, other.DisplayName.Text) == (-1, "l/min")
            backwards = await (await node("flow").get_child("0:EURange")).read_value()
            assert (backwards.Low, backwards.High) == (0.0, 10.0)
            with pytest.raises(ua.UaStatusCodeError):  # no unit: no EngineeringUnits
                await node("setp").get_child("0:EngineeringUnits")
            with pytest.raises(ua.UaStatusCodeError):  # not scaled: a plain variable
                await node("temp").get_child("0:EURange")
            assert (await node("temp").read_type_definition()) == numeric_id(
                ua.ObjectIds.BaseDataVariableType)

    asyncio.run(body())


def test_writes_take_the_data_type_and_scale_back_to_raw(typed_plc: TypedPlc) -> None:
    async def body() -> None:
        async with _client(typed_plc.plc) as client:
            node = await _nodes(client)
            await node("pct").write_value(ua.Variant(25.0, ua.VariantType.Double))
            await _until(lambda: _value_is(node("pct"), 25.0), "pct reads 25.0")
            assert typed_plc.registers(HOLDING_MW + 1, 1) == [6912]  # 25 % of 27648
            await node("temp_c").write_value(ua.Variant(200.0, ua.VariantType.Double))
            await _until(lambda: _value_is(node("temp_c"), 150.0), "clamped to 150 °C")
            assert typed_plc.registers(HOLDING_MW + 2, 1) == [1500]
            await node("count").write_value(ua.Variant(-(1 << 31), ua.VariantType.Int32))
            await node("temp").write_value(ua.Variant(-2.25, ua.VariantType.Float))
            await node("big").write_value(ua.Variant((1 << 32) - 1, ua.VariantType.UInt32))
            await _until(lambda: _value_is(node("big"), (1 << 32) - 1), "big written")
            assert await node("count").read_value() == -(1 << 31)
            assert await node("temp").read_value() == -2.25
            registers = typed_plc.registers(HOLDING_MD + 2, 2)  # %MD1, high word first
            assert registers == [0x8000, 0x0000]

            refused = {"pct": (ua.Variant(150.0, ua.VariantType.Double),  # raw 41472: no int
                               ua.uaerrors.BadOutOfRange),
                       "temp": (ua.Variant(math.nan, ua.VariantType.Float),
                                ua.uaerrors.BadOutOfRange),
                       "small": (ua.Variant(-5, ua.VariantType.Int32),  # not the DataType
                                 ua.uaerrors.BadTypeMismatch),
                       "setp": (ua.Variant(5, ua.VariantType.Int16),  # scaled: a Double
                                ua.uaerrors.BadTypeMismatch)}
            for name, (variant, error) in refused.items():
                with pytest.raises(error):
                    await node(name).write_value(variant)
            # A later write is applied after anything a refusal could have queued.
            await node("small").write_value(ua.Variant(-5, ua.VariantType.Int16))
            await _until(lambda: _value_is(node("small"), -5), "small reads -5")
            assert typed_plc.registers(HOLDING_MW + 1, 1) == [6912]
            assert await node("pct").read_value() == 25.0
            assert await node("temp").read_value() == -2.25
            assert await node("setp").read_value() == 0.0

    asyncio.run(body())


def test_a_nan_real_reads_as_nan(typed_plc: TypedPlc) -> None:
    async def body() -> None:
        async with _client(typed_plc.plc) as client:
            node = await _nodes(client)
            nan_r = node("nan_r")
            typed_plc.write_registers(HOLDING_MD + 4, [0x7FC0, 0x0000])  # %MD2: a quiet NaN
            await _until(lambda: _is_nan(nan_r), "nan_r reads NaN")
            variant = (await nan_r.read_data_value()).Value
            assert variant.VariantType is ua.VariantType.Float
            typed_plc.write_registers(HOLDING_MD + 4, [0xFF80, 0x0000])  # -infinity
            await _until(lambda: _value_is(nan_r, -math.inf), "nan_r reads -inf")

    asyncio.run(body())


async def _is_nan(node: Any) -> bool:
    value = await node.read_value()
    return isinstance(value, float) and math.isnan(value)


DRIVER_IO = """
drivers:
  remote: {{kind: opcua, url: "{url}", user: owner, password_env: SOFTPLC_TEST_TOKEN}}
symbols:
  far_temp:  {{address: "%ID0", type: real, channel: PLC.Symbols.temp}}
  far_count: {{address: "%ID1", type: dint, channel: PLC.Symbols.count}}
  far_pct:   {{address: "%IL0", type: lreal, channel: PLC.Symbols.pct}}
  far_small: {{address: "%IW0", type: int, channel: PLC.Symbols.small}}
  to_wide:   {{address: "%QW0", type: int, channel: PLC.Symbols.wide}}
  to_setp:   {{address: "%QD0", type: real, channel: PLC.Symbols.setp}}
"""


def test_the_driver_moves_typed_values(typed_plc: TypedPlc,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Remote Float, Int32, Double (engineering) and Int16 into typed inputs; a local int
    written as the remote Int32, a local real as a remote scaled symbol's Double."""
    plc = typed_plc.plc

    async def remote_values() -> None:
        async with _client(plc) as client:
            node = await _nodes(client)
            await node("temp").write_value(ua.Variant(3.5, ua.VariantType.Float))
            await node("count").write_value(ua.Variant(-123456, ua.VariantType.Int32))
            await node("small").write_value(ua.Variant(-9, ua.VariantType.Int16))
            await node("pct").write_value(ua.Variant(37.5, ua.VariantType.Double))
            await _until(lambda: _value_is(node("pct"), 37.5), "pct reads 37.5")

    asyncio.run(remote_values())
    monkeypatch.setenv("SOFTPLC_TEST_TOKEN", plc.token)
    io = parse_io_image(DRIVER_IO.format(url=plc.url), "remote.yaml")
    driver = OpcUaIoDriver(io.drivers["remote"], list(io.symbols.values()))
    image = ProcessImage(io.sizes)
    sym = {name: s.address for name, s in io.symbols.items()}
    image.set(sym["to_wide"], -7 & 0xFFFF)
    image.set(sym["to_setp"], struct.unpack("<I", struct.pack("<f", 12.5))[0])

    def value(name: str, fmt: str) -> float:
        raw = image.get(sym[name])
        return float(struct.unpack(fmt, raw.to_bytes(struct.calcsize(fmt), "little"))[0])

    def seen() -> dict[str, float]:
        return {"far_temp": value("far_temp", "<f"), "far_count": value("far_count", "<i"),
                "far_small": value("far_small", "<h"), "far_pct": value("far_pct", "<d")}

    wanted = {"far_temp": 3.5, "far_count": -123456, "far_small": -9, "far_pct": 37.5}
    driver.open()
    try:
        deadline = time.monotonic() + 30
        while seen() != wanted or driver.health() is not Health.OK \
                or typed_plc.registers(HOLDING_MD + 8, 2) != [0xFFFF, 0xFFF9] \
                or typed_plc.registers(HOLDING_MW + 4, 1) != [3456]:
            assert time.monotonic() < deadline, (seen(), driver.health(), driver.problem())
            driver.read_inputs(image, 0)
            driver.write_outputs(image, 0)
            time.sleep(0.05)
    finally:
        driver.close()


@pytest.mark.parametrize(("t", "value", "raw"), [
    (SymType.REAL, 0.1, struct.unpack("<I", struct.pack("<f", 0.1))[0]),
    (SymType.INT, -1, 0xFFFF), (SymType.DINT, -70000.0, -70000 & 0xFFFFFFFF),
    (SymType.BOOL, 1, 1), (SymType.LREAL, math.inf, 0x7FF0000000000000)])
def test_remote_values_into_symbols(t: SymType, value: object, raw: int) -> None:
    assert remote_raw(t, value) == raw


@pytest.mark.parametrize(("t", "value"), [(SymType.INT, 40000), (SymType.WORD, -1),
                                          (SymType.DINT, 1.5), (SymType.REAL, 1e300),
                                          (SymType.UDINT, "7")])
def test_remote_values_that_do_not_fit_are_refused(t: SymType, value: object) -> None:
    with pytest.raises(ValueError):
        remote_raw(t, value)


def test_outputs_take_the_remote_data_type() -> None:
    assert remote_variant(SymType.INT, 0xFFF9, ua.VariantType.Int32) == ua.Variant(
        -7, ua.VariantType.Int32)
    assert remote_variant(SymType.WORD, 300, ua.VariantType.Double).Value == 300.0
    for t, raw, vtype in ((SymType.INT, 0xFFFF, ua.VariantType.UInt16),
                          (SymType.REAL, struct.unpack("<I", struct.pack("<f", 2.5))[0],
                           ua.VariantType.Int32),
                          (SymType.DINT, 70000, ua.VariantType.Int16),
                          (SymType.WORD, 1, ua.VariantType.String)):
        with pytest.raises(ValueError):
            remote_variant(t, raw, vtype)
