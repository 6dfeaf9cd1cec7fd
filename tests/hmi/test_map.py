"""The register map, pure: no sockets, no pymodbus."""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from softplc.core.image import Address, Area, ImageSizes, Width, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import HmiWrite, Status
from softplc.hmi.map import (
    FLAG_STALE,
    STATUS_FAULT_CODE,
    STATUS_FLAGS,
    STATUS_FORCED,
    STATUS_LAST_EXEC_US,
    STATUS_MAX_EXEC_US,
    STATUS_OVERRUNS,
    STATUS_P99_LATENESS_US,
    STATUS_PERIOD_US,
    STATUS_PROGRAM_HASH,
    STATUS_SCAN_COUNT,
    STATUS_STATE,
    STATUS_WORDS,
    ExceptionCode,
    MapError,
    RegisterMap,
    Table,
    status_base,
    status_registers,
)
from tests.hmi.helpers import ImageSource

SIZES = ImageSizes()


def filled() -> ImageSource:
    src = ImageSource(SIZES)
    src.image.qx[[0, 3, 799]] = True
    src.image.mx[[0, 5]] = True
    src.image.ix[[1, 799]] = True
    src.image.iw[:] = range(1024)
    src.image.qw[:] = [1000 + i for i in range(1024)]
    src.image.mw[:] = [(5000 + i) & 0xFFFF for i in range(1024)]
    src.publish()
    return src


def test_table_sizes() -> None:
    m = RegisterMap(SIZES)
    assert m.size(Table.COILS) == 1600
    assert m.size(Table.DISCRETE_INPUTS) == 800
    assert m.size(Table.INPUT_REGISTERS) == 4096 + 4 * 256  # %IL ends it (docs/modbus.md)
    assert m.size(Table.HOLDING_REGISTERS) == 10 * 1024 + 4 * 256  # %QL ends it
    assert status_base(SIZES) == 1024


def test_coils_are_qx_then_mx_with_byte_times_8_plus_bit() -> None:
    src = filled()
    m = RegisterMap(SIZES)
    snap = src.latest()
    assert m.read(snap, Table.COILS, 0, 4) == [1, 0, 0, 1]
    qx_99_7 = parse_address("%QX99.7").index
    assert m.read(snap, Table.COILS, qx_99_7, 1) == [1]
    assert m.read(snap, Table.COILS, 798, 4) == [0, 1, 1, 0]  # %QX99.6 %QX99.7 %MX0.0 %MX0.1
    assert m.read(snap, Table.COILS, 800 + 5, 1) == [1]


def test_discrete_inputs_are_ix() -> None:
    m = RegisterMap(SIZES)
    assert m.read(filled().latest(), Table.DISCRETE_INPUTS, 0, 3) == [0, 1, 0]
    assert m.read(filled().latest(), Table.DISCRETE_INPUTS, 799, 1) == [1]


def test_registers() -> None:
    m, snap = RegisterMap(SIZES), filled().latest()
    assert m.read(snap, Table.INPUT_REGISTERS, 1020, 4) == [1020, 1021, 1022, 1023]
    assert m.read(snap, Table.HOLDING_REGISTERS, 1022, 4) == [2022, 2023, 5000, 5001]
    assert m.read(snap, Table.HOLDING_REGISTERS, 2047, 1) == [(5000 + 1023) & 0xFFFF]


def test_status_block_layout() -> None:
    status = Status(
        state=PlcState.RUNNING,
        scan_count=0x1_0002,
        last_exec_us=7,
        max_exec_us=0x1_0000_0000,  # saturates
        p99_lateness_us=-5,  # clamps at 0
        overruns=3,
        program_hash="0123456789abcdef" + "f" * 48,
        fault_code=1,
        period_us=10_000,
    )
    words = status_registers(status)
    assert len(words) == STATUS_WORDS
    assert words[STATUS_STATE] == 2
    assert words[STATUS_FAULT_CODE] == 1
    assert words[STATUS_SCAN_COUNT : STATUS_SCAN_COUNT + 2] == [1, 2]
    assert words[STATUS_LAST_EXEC_US : STATUS_LAST_EXEC_US + 2] == [0, 7]
    assert words[STATUS_MAX_EXEC_US : STATUS_MAX_EXEC_US + 2] == [0xFFFF, 0xFFFF]
    assert words[STATUS_P99_LATENESS_US : STATUS_P99_LATENESS_US + 2] == [0, 0]
    assert words[STATUS_OVERRUNS : STATUS_OVERRUNS + 2] == [0, 3]
    assert words[STATUS_PERIOD_US : STATUS_PERIOD_US + 2] == [0, 10_000]
    assert words[STATUS_PROGRAM_HASH : STATUS_PROGRAM_HASH + 4] == [0x0123, 0x4567, 0x89AB, 0xCDEF]
    assert status_registers(Status())[STATUS_PROGRAM_HASH : STATUS_PROGRAM_HASH + 4] == [0] * 4
    # Appended after the hash (never renumbered): forced count, then flags.
    assert STATUS_FORCED == STATUS_PROGRAM_HASH + 4 == STATUS_FLAGS - 1 == STATUS_WORDS - 2
    assert words[STATUS_FORCED] == 0
    assert status_registers(Status(forced=3))[STATUS_FORCED] == 3
    assert status_registers(Status(forced=70_000))[STATUS_FORCED] == 0xFFFF
    assert words[STATUS_FLAGS] == 0
    assert status_registers(replace(status, stale=True))[STATUS_FLAGS] == FLAG_STALE


def test_status_block_is_read_through_input_registers() -> None:
    src = ImageSource(SIZES, Status(state=PlcState.FAULTED, fault_code=2))
    src.image.iw[1023] = 42
    src.publish()
    m = RegisterMap(SIZES)
    words = m.read(src.latest(), Table.INPUT_REGISTERS, 1023, 4)
    assert words == [42, int(PlcState.FAULTED), 2, 0]
    whole = m.read(src.latest(), Table.INPUT_REGISTERS, 1024, STATUS_WORDS)
    assert whole == status_registers(src.latest().status)


@pytest.mark.parametrize(
    ("table", "address", "count"),
    [
        (Table.COILS, 1600, 1),
        (Table.COILS, 1599, 2),
        (Table.DISCRETE_INPUTS, 800, 1),
        (Table.DISCRETE_INPUTS, 0, 801),
        (Table.INPUT_REGISTERS, 1024 + STATUS_WORDS, 1),
        (Table.INPUT_REGISTERS, 1024 + STATUS_WORDS - 2, 3),
        (Table.HOLDING_REGISTERS, 11264, 1),
        (Table.HOLDING_REGISTERS, 2048 + 512, 1),  # the gap after %MD255
        (Table.HOLDING_REGISTERS, 65535, 1),
    ],
)
def test_read_beyond_the_map_is_02(table: Table, address: int, count: int) -> None:
    with pytest.raises(MapError) as err:
        RegisterMap(SIZES).read(filled().latest(), table, address, count)
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_ADDRESS


def test_read_quantity_zero_is_03() -> None:
    with pytest.raises(MapError) as err:
        RegisterMap(SIZES).read(filled().latest(), Table.COILS, 0, 0)
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_VALUE


def test_snapshot_of_other_sizes_is_04() -> None:
    src = ImageSource(ImageSizes(bits=16, words=4))
    with pytest.raises(MapError) as err:
        RegisterMap(SIZES).read(src.latest(), Table.COILS, 0, 1)
    assert err.value.code is ExceptionCode.SERVER_DEVICE_FAILURE


def test_plan_write_splits_per_iec_area() -> None:
    m = RegisterMap(SIZES)
    assert m.plan_write(Table.COILS, 798, [1, 0, 1]) == [
        HmiWrite(Address(Area.OUTPUT, Width.BIT, 798), (1, 0)),
        HmiWrite(Address(Area.MEMORY, Width.BIT, 0), (1,)),
    ]
    assert m.plan_write(Table.HOLDING_REGISTERS, 1030, [7, 8]) == [
        HmiWrite(parse_address("%MW6"), (7, 8)),
    ]
    assert m.plan_write(Table.HOLDING_REGISTERS, 5, [65535]) == [
        HmiWrite(parse_address("%QW5"), (65535,)),
    ]


@pytest.mark.parametrize("table", [Table.DISCRETE_INPUTS, Table.INPUT_REGISTERS])
def test_read_only_tables_cannot_be_written(table: Table) -> None:
    with pytest.raises(MapError) as err:
        RegisterMap(SIZES).plan_write(table, 0, [1])
    assert err.value.code is ExceptionCode.ILLEGAL_FUNCTION


def test_write_beyond_the_map_is_02_and_values_out_of_range_03() -> None:
    m = RegisterMap(SIZES)
    with pytest.raises(MapError) as err:
        m.plan_write(Table.HOLDING_REGISTERS, 2047, [1, 2])
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_ADDRESS
    with pytest.raises(MapError) as err:
        m.plan_write(Table.COILS, 0, [2])
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_VALUE
    with pytest.raises(MapError) as err:
        m.plan_write(Table.HOLDING_REGISTERS, 0, [0x10000])
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_VALUE
    with pytest.raises(MapError) as err:
        m.plan_write(Table.HOLDING_REGISTERS, 0, [])
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_VALUE


def test_writable_predicate_is_all_or_nothing() -> None:
    def only_memory(address: Address) -> bool:
        return address.area is Area.MEMORY

    m = RegisterMap(SIZES, writable=only_memory)
    assert m.plan_write(Table.COILS, 800, [1, 1]) == [
        HmiWrite(Address(Area.MEMORY, Width.BIT, 0), (1, 1))
    ]
    with pytest.raises(MapError) as err:
        m.plan_write(Table.COILS, 799, [1, 1])  # %QX99.7 refused, so %MX0.0 is not written
    assert err.value.code is ExceptionCode.ILLEGAL_DATA_ADDRESS


def test_read_only_map_refuses_every_write_with_02() -> None:
    m = RegisterMap(SIZES, read_only=True)
    for table in (Table.COILS, Table.HOLDING_REGISTERS):
        with pytest.raises(MapError) as err:
            m.plan_write(table, 0, [1])
        assert err.value.code is ExceptionCode.ILLEGAL_DATA_ADDRESS
    assert m.read(filled().latest(), Table.HOLDING_REGISTERS, 0, 1) == [1000]


@given(
    table=st.sampled_from([Table.COILS, Table.HOLDING_REGISTERS]),
    address=st.integers(0, 2047),
    count=st.integers(1, 125),
    seed=st.integers(0, 2**16),
)
def test_planned_writes_read_back_after_publish(
    table: Table, address: int, count: int, seed: int
) -> None:
    sizes = ImageSizes(bits=1024, words=1024)
    m = RegisterMap(sizes)
    top = 1 if table is Table.COILS else 0xFFFF
    values = [(seed * (i + 7) * 2654435761) % (top + 1) for i in range(count)]
    if address + count > m.size(table):
        with pytest.raises(MapError):
            m.plan_write(table, address, values)
        return
    src = ImageSource(sizes)
    try:
        writes = m.plan_write(table, address, values)
    except MapError:  # only a gap or part of a 32/64-bit value beyond %MW: docs/modbus.md
        assert table is Table.HOLDING_REGISTERS and address + count > 2 * sizes.words
        return
    assert sum(len(w.values) for w in writes) == count
    assert len({(w.address.area, w.address.width) for w in writes}) == len(writes)
    for w in writes:
        src.sink(w)
    src.publish()
    assert m.read(src.latest(), table, address, count) == values


def test_a_tiny_image_puts_the_input_long_words_after_its_double_words() -> None:
    """Issue 43: words = 8 (below the status block's 20): %ID after the status block at 28,
    its 8 double words take 16 registers, so %IL starts at 44, past 4 * words (32)."""
    from softplc.hmi.map import long_bases
    hr, ir = Table.HOLDING_REGISTERS, Table.INPUT_REGISTERS
    bases = {f"%{area.value}{width.value}": at for (area, width), at in
             long_bases(ImageSizes(bits=16, words=8)).items()}
    assert bases == {"%MD": (hr, 16), "%ML": (hr, 32), "%QD": (hr, 64), "%QL": (hr, 80),
                     "%ID": (ir, 28), "%IL": (ir, 44)}


def test_where_names_the_iec_address_at_a_modbus_address() -> None:
    m = RegisterMap(ImageSizes())
    hr, ir = Table.HOLDING_REGISTERS, Table.INPUT_REGISTERS
    assert m.where(hr, 1028) == "%MW4"  # the write audit's example
    assert m.where(hr, 2052) == m.where(hr, 2053) == "%MD2"  # by its first register
    assert m.where(ir, 5000) == "%IL226"
    assert m.where(hr, 4095) is None  # past %MD's 256 double words, before %ML


def test_half_a_double_word_written_is_refused_naming_it() -> None:
    m = RegisterMap(ImageSizes())
    hr = Table.HOLDING_REGISTERS
    assert m.plan_write(hr, 2052, [1, 2]) == [HmiWrite(parse_address("%MD2"), (1, 2))]
    for address, count in ((2053, 1), (2052, 1), (2053, 2)):
        with pytest.raises(MapError, match=r"^%MD2 is written whole: its 2 registers in one "
                           "request$") as err:
            m.plan_write(hr, address, [1] * count)
        assert err.value.code is ExceptionCode.ILLEGAL_DATA_ADDRESS
