"""The Modbus register map for HMIs: Modbus tables and 0-based addresses <-> IEC areas.

Owns: the four tables and their segments (OpenPLC-compatible, docs/design.md section 6), the
status block layout, read range checks, and turning an HMI write into journal entries; the
registers of symbols served in engineering units go through eng.py both ways.
Does not know: sockets, frames, function codes, pymodbus, when writes are applied.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass

from softplc.core.datatypes import SymType
from softplc.core.errors import SoftplcError
from softplc.core.image import WORD_MAX, Address, Area, ImageSizes, Width, split_registers
from softplc.core.nonfinite import refusal
from softplc.core.present import ValueRefused
from softplc.core.snapshot import HmiWrite, Snapshot, Status
from softplc.hmi.eng import EngTable, Presentation, join_registers
from softplc.security.decide import Identity, granted
from softplc.security.roles import Act, Role, needs


class Table(enum.Enum):
    COILS = "coils"
    DISCRETE_INPUTS = "discrete inputs"
    INPUT_REGISTERS = "input registers"
    HOLDING_REGISTERS = "holding registers"


class ExceptionCode(enum.IntEnum):
    """Modbus exception codes (Modbus Application Protocol V1.1b3, section 7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06  # Modbus/TCP Security: the audit trail cannot keep up (secure.py)


class MapError(SoftplcError):
    """A request the map refuses; `code` is the Modbus exception to answer with."""

    def __init__(self, code: ExceptionCode, message: str) -> None:
        super().__init__(message)
        self.code = code


# Status block: input registers from `status_base(sizes)` (= sizes.words, 1024 by default).
# Offsets are relative to the base. u32 values take two registers, high word first, and
# saturate at 0xFFFFFFFF.
STATUS_STATE = 0  # PlcState as an int
STATUS_FAULT_CODE = 1  # a FaultCode: 0 none, 1 watchdog, 2 device, 3 program, 4 limit, ...
STATUS_SCAN_COUNT = 2  # u32
STATUS_LAST_EXEC_US = 4  # u32
STATUS_MAX_EXEC_US = 6  # u32
STATUS_P99_LATENESS_US = 8  # u32
STATUS_OVERRUNS = 10  # u32
STATUS_PERIOD_US = 12  # u32
STATUS_PROGRAM_HASH = 14  # first 64 bits of the sha256, 4 registers, high word first
STATUS_FORCED = 18  # how many symbols are forced (0: none), saturates at 65535
STATUS_FLAGS = 19  # bit 0: stale (the scan process has not published for too long);
# bit 1: waiting for I/O (a device has not delivered its first input image: no firing round)
STATUS_WORDS = 20
FLAG_STALE = 1
FLAG_WAITING_IO = 2

U32_MAX = 0xFFFFFFFF

Writable = Callable[[Address], bool]


def status_base(sizes: ImageSizes) -> int:
    """First input register of the status block."""
    return sizes.words


def _u32(value: int) -> list[int]:
    v = min(max(int(value), 0), U32_MAX)
    return [v >> 16, v & WORD_MAX]


def _hash_words(program_hash: str) -> list[int]:
    if not program_hash:
        return [0, 0, 0, 0]
    v = int(program_hash[:16], 16)
    return [(v >> shift) & WORD_MAX for shift in (48, 32, 16, 0)]


def status_registers(status: Status) -> list[int]:
    """The status block as STATUS_WORDS register values."""
    words = [int(status.state), min(max(status.fault_code, 0), WORD_MAX)]
    for value in (
        status.scan_count,
        status.last_exec_us,
        status.max_exec_us,
        status.p99_lateness_us,
        status.overruns,
        status.period_us,
    ):
        words += _u32(value)
    return words + _hash_words(status.program_hash) + [
        min(max(status.forced, 0), WORD_MAX),
        (FLAG_STALE if status.stale else 0) | (FLAG_WAITING_IO if status.waiting_for_io else 0)]


@dataclass(frozen=True, slots=True)
class _Segment:
    """A run of one table backed by one IEC area; `area` None is the status block. `length`
    counts registers (or bits); a double word takes 2 registers, a long word 4."""

    start: int
    length: int
    area: Area | None
    width: Width

    @property
    def per(self) -> int:
        return _REGISTERS[self.width]

    @property
    def end(self) -> int:
        return self.start + self.length


@dataclass(frozen=True, slots=True)
class _Piece:
    """The part of a request [address, address + count) that falls in one segment."""

    segment: _Segment
    offset: int  # index in the IEC area
    first: int  # index in the request's values
    count: int


_REGISTERS = {Width.BIT: 1, Width.WORD: 1, Width.DWORD: 2, Width.LWORD: 4}


def long_bases(sizes: ImageSizes) -> dict[tuple[Area, Width], tuple[Table, int]]:
    """Where the 32/64-bit areas start (docs/modbus.md): %MD at holding register 2 * words
    and %ML at 4 * words, as OpenPLC (2048 and 4096 by default); %QD at 8 * words and %QL at
    10 * words after them; %ID and %IL in the input registers at the same places as %MD and
    %ML (after the status block when the image is tiny)."""
    words, dwords = sizes.words, sizes.dwords
    input_d = max(2 * words, words + STATUS_WORDS)
    hr, ir, d, lw = Table.HOLDING_REGISTERS, Table.INPUT_REGISTERS, Width.DWORD, Width.LWORD
    return {(Area.MEMORY, d): (hr, 2 * words), (Area.MEMORY, lw): (hr, 4 * words),
            (Area.OUTPUT, d): (hr, 8 * words), (Area.OUTPUT, lw): (hr, 10 * words),
            (Area.INPUT, d): (ir, input_d),
            (Area.INPUT, lw): (ir, max(4 * words, input_d + 2 * dwords))}


def _segments(sizes: ImageSizes) -> dict[Table, tuple[_Segment, ...]]:
    bits, words = sizes.bits, sizes.words
    X, W = Width.BIT, Width.WORD
    longs: dict[Table, list[_Segment]] = {Table.HOLDING_REGISTERS: [], Table.INPUT_REGISTERS: []}
    for (area, width), (table, start) in long_bases(sizes).items():
        count = sizes.dwords if width is Width.DWORD else sizes.lwords
        longs[table].append(_Segment(start, count * _REGISTERS[width], area, width))
    return {
        Table.COILS: (
            _Segment(0, bits, Area.OUTPUT, X),
            _Segment(bits, bits, Area.MEMORY, X),
        ),
        Table.DISCRETE_INPUTS: (_Segment(0, bits, Area.INPUT, X),),
        Table.INPUT_REGISTERS: (
            _Segment(0, words, Area.INPUT, W),
            _Segment(words, STATUS_WORDS, None, W),
            *sorted(longs[Table.INPUT_REGISTERS], key=lambda s: s.start),
        ),
        Table.HOLDING_REGISTERS: (
            _Segment(0, words, Area.OUTPUT, W),
            _Segment(words, words, Area.MEMORY, W),
            *sorted(longs[Table.HOLDING_REGISTERS], key=lambda s: s.start),
        ),
    }


_WRITABLE_TABLES = (Table.COILS, Table.HOLDING_REGISTERS)


class RegisterMap:
    """Modbus tables over a process image of `sizes`. Every method is pure: reads take the
    snapshot to answer from, writes return the journal entries and change nothing."""

    def __init__(
        self, sizes: ImageSizes, *, writable: Writable | None = None, read_only: bool = False,
        presentation: Presentation | None = None,
    ) -> None:
        self.sizes = sizes
        self._policy = Identity(None, "policy",
                                granted=Role.VIEWER if read_only else needs(Act.WRITE))
        self._writable = writable
        self._presentation = presentation  # None: every register is raw
        self._segments = _segments(sizes)

    def size(self, table: Table) -> int:
        """Number of addresses of `table`; valid addresses are 0 .. size - 1."""
        return self._segments[table][-1].end

    def read(self, snapshot: Snapshot, table: Table, address: int, count: int) -> list[int]:
        """Values of `count` consecutive addresses (bits as 0/1) from the published scan."""
        if snapshot.image.sizes != self.sizes:
            raise MapError(
                ExceptionCode.SERVER_DEVICE_FAILURE,
                f"snapshot image {snapshot.image.sizes} does not match the map {self.sizes}",
            )
        pieces = list(self._pieces(table, address, count))
        eng = None
        if self._presentation is not None and table is not Table.COILS \
                and table is not Table.DISCRETE_INPUTS:
            eng = self._presentation(snapshot.status.program_hash)  # the snapshot's program
        values: list[int] = []
        for piece in pieces:
            values += _read_piece(snapshot, piece, eng)
        return values

    def plan_write(self, table: Table, address: int, values: Sequence[int]) -> list[HmiWrite]:
        """The journal entries for an HMI write, one per IEC area it touches. All or nothing:
        raises MapError when any address is outside the map or not writable."""
        if table not in _WRITABLE_TABLES:
            raise MapError(ExceptionCode.ILLEGAL_FUNCTION, f"{table.value} are read-only")
        _check_values(table, values)
        pieces = list(self._pieces(table, address, len(values)))
        # Plain Modbus has no users: its write policy grants the role (security/decide.py)
        if not granted(self._policy, Act.WRITE).allowed:
            raise MapError(ExceptionCode.ILLEGAL_DATA_ADDRESS, "the Modbus slave is read-only")
        writes = [_journal_entry(piece, values) for piece in pieces]
        for write in writes:
            self._check_writable(write)
        if self._presentation is None or table is Table.COILS:
            return writes
        eng = self._presentation(None)  # the program the latest snapshot runs
        if eng.stale:  # its registers' presentation is not known yet: never store a guess
            raise MapError(ExceptionCode.SERVER_DEVICE_BUSY, "a new program is being loaded "
                           "and how it presents its registers is not known yet: retry")
        return [_raw_write(write, eng) for write in writes]

    def where(self, table: Table, address: int) -> str | None:
        """The IEC address at a Modbus address (`%MW4` for holding register 1028 by
        default; a double or long word by its first register), None outside the areas."""
        for piece in _overlaps(self._segments[table], address, address + 1):
            seg = piece.segment
            if seg.area is not None:
                return str(Address(seg.area, seg.width, piece.offset // seg.per))
        return None

    def _check_writable(self, write: HmiWrite) -> None:
        if self._writable is None:
            return
        first = write.address
        for i in range(len(write.values) // _REGISTERS[first.width]):
            where = Address(first.area, first.width, first.index + i)
            if not self._writable(where):
                raise MapError(ExceptionCode.ILLEGAL_DATA_ADDRESS, f"{where} is not writable")

    def _pieces(self, table: Table, address: int, count: int) -> Iterator[_Piece]:
        if count < 1:
            raise MapError(ExceptionCode.ILLEGAL_DATA_VALUE, f"quantity {count} is not >= 1")
        end = address + count
        if address < 0 or end > self.size(table):
            raise MapError(
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
                f"{table.value} {address}..{end - 1} outside 0..{self.size(table) - 1}",
            )
        pieces = list(_overlaps(self._segments[table], address, end))
        if sum(p.count for p in pieces) != count:  # a gap between the areas
            raise MapError(ExceptionCode.ILLEGAL_DATA_ADDRESS,
                           f"{table.value} {address}..{end - 1} reach registers of no area")
        return iter(pieces)


def _overlaps(segments: Sequence[_Segment], address: int, end: int) -> Iterator[_Piece]:
    for seg in segments:
        lo, hi = max(address, seg.start), min(end, seg.end)
        if lo < hi:
            yield _Piece(seg, lo - seg.start, lo - address, hi - lo)


def _read_piece(snapshot: Snapshot, piece: _Piece, eng: EngTable | None) -> list[int]:
    seg, lo, hi = piece.segment, piece.offset, piece.offset + piece.count
    if seg.area is None:
        return status_registers(snapshot.status)[lo:hi]
    area = snapshot.image.area(seg.area, seg.width)
    per = seg.per
    first_index = lo // per
    raws = [int(v) for v in area[first_index : -(-hi // per)].tolist()]
    shown = eng.area(seg.area, seg.width) if eng is not None else None
    for index, sym in (shown or {}).items():  # scaled symbols served in engineering units
        if first_index <= index < first_index + len(raws):
            raws[index - first_index] = sym.register(raws[index - first_index])
    if per == 1:
        return raws
    registers: list[int] = []
    for raw in raws:
        registers += split_registers(raw, seg.width)
    first = lo // per * per
    return registers[lo - first : hi - first]


def _journal_entry(piece: _Piece, values: Sequence[int]) -> HmiWrite:
    """One entry per area; a double or long word only whole (its 2 or 4 registers in this
    request), so the scan applies it in one piece: never half a value."""
    seg = piece.segment
    assert seg.area is not None, "writable tables have no status segment"
    per = seg.per
    if piece.offset % per or piece.count % per:
        name = Address(seg.area, seg.width, piece.offset // per)
        raise MapError(ExceptionCode.ILLEGAL_DATA_ADDRESS,
                       f"{name} is written whole: its {per} registers in one request")
    chunk = tuple(int(v) for v in values[piece.first : piece.first + piece.count])
    return HmiWrite(Address(seg.area, seg.width, piece.offset // per), chunk)


def _raw_write(write: HmiWrite, eng: EngTable) -> HmiWrite:
    """`write` with the registers of symbols served in engineering units converted back to
    the raw bits they store (eng.py); 03 for a value the symbol cannot take."""
    floats = eng.finite(write.address.area, write.address.width)
    if floats:
        _check_finite(write, floats)
    shown = eng.area(write.address.area, write.address.width)
    if not shown:
        return write
    per, first = _REGISTERS[write.address.width], write.address
    values = list(write.values)
    for i in range(len(values) // per):
        sym = shown.get(first.index + i)
        if sym is None:
            continue
        where = Address(first.area, first.width, first.index + i)
        try:
            raw = sym.raw(join_registers(tuple(values[i * per : (i + 1) * per])))
        except ValueRefused as exc:
            raise MapError(ExceptionCode.ILLEGAL_DATA_VALUE, f"{where}: {exc}") from None
        values[i * per : (i + 1) * per] = split_registers(raw, first.width)
    return HmiWrite(first, tuple(values))


def _check_finite(write: HmiWrite, floats: Mapping[int, tuple[str, SymType]]) -> None:
    """03 for the raw bits of a NaN or an infinity written to a real or lreal symbol that
    refuses them (core/nonfinite.py: all but `finite: false`)."""
    per, first = _REGISTERS[write.address.width], write.address
    for i in range(len(write.values) // per):
        held = floats.get(first.index + i)
        if held is None:
            continue
        problem = refusal(*held, join_registers(write.values[i * per : (i + 1) * per]))
        if problem is not None:
            where = Address(first.area, first.width, first.index + i)
            raise MapError(ExceptionCode.ILLEGAL_DATA_VALUE, f"{where}: {problem}")


def _check_values(table: Table, values: Sequence[int]) -> None:
    top = 1 if table is Table.COILS else WORD_MAX
    for v in values:
        if not 0 <= v <= top:
            raise MapError(ExceptionCode.ILLEGAL_DATA_VALUE, f"value {v} is not in 0..{top}")
