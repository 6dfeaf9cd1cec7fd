"""Process image: bit, word, double-word and long-word areas, and IEC 61131-3 addresses.

Owns: the twelve areas (%IX %QX %MX bits, %IW %QW %MW 16-bit words, %ID %QD %MD 32-bit double
words, %IL %QL %ML 64-bit long words, each its own region as OpenPLC has them), address
parsing and formatting (including the seed paper's short forms I1.2, O5.3/Q5.3, M0.1), bounds
checks, snapshots. Areas hold raw unsigned bits; core/datatypes.py says what they mean.
Does not know: symbols files, drivers, Modbus, clocks.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from softplc.core.errors import SoftplcError

BoolArray = npt.NDArray[np.bool_]
WordArray = npt.NDArray[np.uint16]
AreaArray = npt.NDArray[Any]  # any area: bool, uint16, uint32 or uint64

WORD_MAX = 0xFFFF
AREAS = ("ix", "qx", "mx", "iw", "qw", "mw", "id", "qd", "md", "il", "ql", "ml")
INPUT_AREAS = ("ix", "iw", "id", "il")
# What a scan writes: outputs and memory. The 32/64-bit areas (issue 30) come last, so a
# digest over the first four is what it was before them (runtime/trace.py).
OUTPUT_AREAS = ("qx", "qw", "mx", "mw", "qd", "md", "ql", "ml")
RAW_MAX = {"x": 1, "w": WORD_MAX, "d": 0xFFFFFFFF, "l": (1 << 64) - 1}  # by width letter


class AddressError(SoftplcError, ValueError):
    """An IEC address that does not parse or lies outside the configured image."""


class Area(enum.Enum):
    INPUT = "I"
    OUTPUT = "Q"
    MEMORY = "M"


class Width(enum.Enum):
    BIT = "X"
    WORD = "W"
    DWORD = "D"  # 32 bits: dint, udint, real
    LWORD = "L"  # 64 bits: lreal


@dataclass(frozen=True, slots=True, order=True)
class Address:
    """One location of the image. For bits `index` is byte * 8 + bit."""

    area: Area
    width: Width
    index: int
    attr: str = field(init=False, compare=False, repr=False)  # "ix", "qw", ...: the array

    def __post_init__(self) -> None:
        object.__setattr__(self, "attr", self.area.value.lower() + self.width.value.lower())

    def __str__(self) -> str:
        if self.width is Width.BIT:
            return f"%{self.area.value}X{self.index // 8}.{self.index % 8}"
        return f"%{self.area.value}{self.width.value}{self.index}"

    @property
    def is_bit(self) -> bool:
        return self.width is Width.BIT


_IEC = re.compile(r"%([IQM])([XWDL]?)(\d+)(?:\.(\d+))?")
_SHORT = re.compile(r"([IQOM])([WDL]?)(\d+)(?:\.(\d+))?")


def parse_address(text: str) -> Address:
    """Parse `%IX0.0`, `%QW3`, `%MD2`, `%ML0`, `%MX1.7` or a short form (`I1.2`, `O5.3`,
    `Q5.3`, `M0.1`, `IW4`, `MD2`)."""
    raw = text.strip().upper()
    m = _IEC.fullmatch(raw)
    if m is None:
        m = _SHORT.fullmatch(raw)
        if m is None:
            raise AddressError(
                f"bad address {text!r}: expected %IX<byte>.<bit>, %QW<n>, %MD<n>, %ML<n>, "
                "%MX.., or I1.2 / Q5.3 / M0.1"
            )
    letter, width_letter, major, minor = m.groups()
    area = Area("Q" if letter == "O" else letter)
    if width_letter in ("W", "D", "L"):
        if minor is not None:
            raise AddressError(f"bad address {text!r}: a word address has no .bit part")
        return Address(area, Width(width_letter), int(major))
    if minor is None:
        raise AddressError(f"bad address {text!r}: a bit address needs <byte>.<bit>, e.g. %IX0.3")
    byte, bit = int(major), int(minor)
    if bit > 7:
        raise AddressError(f"bad address {text!r}: bit {bit} is not in 0..7")
    return Address(area, Width.BIT, byte * 8 + bit)


_LONG_DEFAULT = 256


@dataclass(frozen=True, slots=True)
class ImageSizes:
    """Area sizes. Defaults follow OpenPLC: %IX/%QX 0.0..99.7, %IW/%QW/%MW 0..1023; 256
    double words (%ID %QD %MD 0..255) and 256 long words (%IL %QL %ML 0..255) per area, a
    quarter of OpenPLC's 1024 so that the image every scan copies and publishes stays small
    (docs/design.md section 5). At most `words` each: the Modbus map puts %MD at register
    2 * words and %ML at 4 * words (OpenPLC's 2048 and 4096)."""

    bits: int = 800
    words: int = 1024
    dwords: int = -1  # -1: the default, min(256, words)
    lwords: int = -1

    def __post_init__(self) -> None:
        if self.bits <= 0 or self.bits % 16 or self.words <= 0:
            raise ValueError("image sizes: bits must be a positive multiple of 16, words positive")
        for name in ("dwords", "lwords"):
            if getattr(self, name) == -1:
                object.__setattr__(self, name, min(_LONG_DEFAULT, self.words))
        if not (0 <= self.dwords <= self.words and 0 <= self.lwords <= self.words):
            raise ValueError("image sizes: dwords and lwords must be 0..words")


class ProcessImage:
    """Inputs, outputs and memory. Arrays are public so that drivers and the HMI map can
    move whole ranges with numpy; single locations go through get/set, which check bounds."""

    __slots__ = ("_ins", "_ins_mv", "_mv", "_outs", "buf", "id", "il", "iw", "ix", "md", "ml",
                 "mw", "mx", "qd", "ql", "qw", "qx", "sizes")
    ix: BoolArray
    qx: BoolArray
    mx: BoolArray
    iw: WordArray
    qw: WordArray
    mw: WordArray
    id: npt.NDArray[np.uint32]
    qd: npt.NDArray[np.uint32]
    md: npt.NDArray[np.uint32]
    il: npt.NDArray[np.uint64]
    ql: npt.NDArray[np.uint64]
    ml: npt.NDArray[np.uint64]

    def __init__(self, sizes: ImageSizes | None = None) -> None:
        self.sizes = sizes or ImageSizes()
        # One buffer for all six areas (views into it), inputs first and the four output
        # areas last and contiguous: a scan copies, compares and digests its image with one
        # numpy call each instead of one per area (issue 15.5). `buf` is None for an image
        # whose areas are separate arrays (a shared-memory snapshot's decoded copy).
        self.buf: npt.NDArray[np.uint8] | None = np.zeros(_buffer_bytes(self.sizes), np.uint8)
        self._views()

    def _views(self) -> None:
        assert self.buf is not None
        buf, at = self.buf, 0
        for name, nbytes, dtype in _layout(self.sizes):
            setattr(self, name, buf[at:at + nbytes].view(dtype))
            at += nbytes
        # The input part and the output part of the buffer, sliced once, not every scan.
        n = _inputs_bytes(self.sizes)
        self._ins, self._outs = buf[:n], buf[n:]
        # Copies between memoryviews are a plain memcpy, about half of np.copyto's cost here.
        self._mv, self._ins_mv = buf.data, self._ins.data

    def area(self, area: Area, width: Width) -> AreaArray:
        arr: AreaArray = getattr(self, area.value.lower() + width.value.lower())
        return arr

    def check(self, address: Address) -> None:
        size = len(getattr(self, address.attr))
        if not 0 <= address.index < size:
            raise AddressError(f"address {address} is outside the image (size {size})")

    def get(self, address: Address) -> int:
        arr = getattr(self, address.attr)
        if not 0 <= address.index < len(arr):
            self.check(address)
        return int(arr[address.index])

    def set(self, address: Address, value: int) -> None:
        """Store raw bits: words wrap to 16 bits, double and long words to 32 and 64 (the typed
        writes of a program go through core/datatypes.py first), bits take its truth value."""
        arr = getattr(self, address.attr)
        if not 0 <= address.index < len(arr):
            self.check(address)
        arr[address.index] = bool(value) if arr.dtype == np.bool_ else (
            int(value) & RAW_MAX[address.attr[1]])

    def write_registers(self, address: Address, values: Sequence[int]) -> None:
        """An HMI write from `address` on: bits take truth values, words 16-bit registers; a
        double or long word takes 2 or 4 registers, most significant first (the Modbus map's
        order), and only whole ones (hmi/map.py refuses a part)."""
        arr = self.area(address.area, address.width)
        start, per = address.index, _REGISTERS[address.width]
        if per > 1:
            values = [_join_registers(values[i:i + per]) for i in range(0, len(values), per)]
        chunk = np.asarray(list(values[: max(len(arr) - start, 0)]), dtype=np.uint64)
        if address.is_bit:
            arr[start:start + len(chunk)] = chunk != 0
        else:
            arr[start:start + len(chunk)] = chunk & RAW_MAX[address.attr[1]]

    def copy(self) -> ProcessImage:
        dup = ProcessImage.__new__(ProcessImage)
        dup.sizes = self.sizes
        if self.buf is not None:
            dup.buf = self.buf.copy()
            dup._views()
            return dup
        dup.buf = None
        for name in AREAS:
            setattr(dup, name, getattr(self, name).copy())
        return dup

    def copy_into(self, other: ProcessImage) -> None:
        """Overwrite `other` (same sizes) with this image, without allocating."""
        if self.buf is not None and other.buf is not None:
            other._mv[:] = self._mv
            return
        for name in AREAS:
            np.copyto(getattr(other, name), getattr(self, name))

    def latch_inputs(self, source: ProcessImage) -> None:
        """Copy the input areas (%IX, %IW, %ID, %IL) of `source` (same sizes) into this image."""
        if self.buf is not None and source.buf is not None:
            self._ins_mv[:] = source._ins_mv
            return
        for name in INPUT_AREAS:
            np.copyto(getattr(self, name), getattr(source, name))

    def inputs_bytes(self) -> bytes:
        """The input areas (INPUT_AREAS) as bytes, for comparing."""
        if self.buf is not None:
            return self._ins.tobytes()
        return b"".join(getattr(self, n).tobytes() for n in INPUT_AREAS)

    def outputs_bytes(self) -> bytes:
        """The output and memory areas (OUTPUT_AREAS) as bytes, for comparing and digests."""
        if self.buf is not None:
            return self._outs.tobytes()
        return b"".join(getattr(self, n).tobytes() for n in _BUFFER_OUTPUTS)

    def __reduce__(self) -> tuple[Any, tuple[ImageSizes, dict[str, npt.NDArray[Any]]]]:
        """Pickled as sizes and contents: the areas are views into one buffer (and the
        memoryviews cannot be pickled), so an unpickled image builds its buffer anew."""
        return (_rebuild, (self.sizes, {name: getattr(self, name).copy() for name in AREAS}))

    def equals(self, other: ProcessImage) -> bool:
        return all(np.array_equal(getattr(self, n), getattr(other, n)) for n in AREAS)


_REGISTERS = {Width.BIT: 1, Width.WORD: 1, Width.DWORD: 2, Width.LWORD: 4}


def _join_registers(registers: Sequence[int]) -> int:
    raw = 0
    for register in registers:
        raw = (raw << 16) | (int(register) & WORD_MAX)
    return raw


def split_registers(raw: int, width: Width) -> list[int]:
    """The Modbus registers of one raw value, most significant first."""
    count = _REGISTERS[width]
    return [(int(raw) >> (16 * (count - 1 - i))) & WORD_MAX for i in range(count)]


# Buffer order: inputs, then the output areas (what a scan writes) in one contiguous tail.
_BUFFER_OUTPUTS = ("qx", "mx", "qw", "mw", "qd", "md", "ql", "ml")


def _layout(sizes: ImageSizes) -> tuple[tuple[str, int, type[np.generic]], ...]:
    bits, words, dwords, lwords = sizes.bits, 2 * sizes.words, 4 * sizes.dwords, 8 * sizes.lwords
    return (("ix", bits, np.bool_), ("iw", words, np.uint16), ("id", dwords, np.uint32),
            ("il", lwords, np.uint64), ("qx", bits, np.bool_), ("mx", bits, np.bool_),
            ("qw", words, np.uint16), ("mw", words, np.uint16), ("qd", dwords, np.uint32),
            ("md", dwords, np.uint32), ("ql", lwords, np.uint64), ("ml", lwords, np.uint64))


def image_offsets(sizes: ImageSizes) -> dict[str, tuple[int, int]]:
    """Each area's (start, stop) byte offsets in a ProcessImage's buffer (`buf`)."""
    offsets, at = {}, 0
    for name, nbytes, _ in _layout(sizes):
        offsets[name] = (at, at + nbytes)
        at += nbytes
    return offsets


def _rebuild(sizes: ImageSizes, areas: dict[str, npt.NDArray[Any]]) -> ProcessImage:
    image = ProcessImage(sizes)
    for name, values in areas.items():
        np.copyto(getattr(image, name), values)
    return image


def _inputs_bytes(sizes: ImageSizes) -> int:
    return sizes.bits + 2 * sizes.words + 4 * sizes.dwords + 8 * sizes.lwords


def _buffer_bytes(sizes: ImageSizes) -> int:
    return 3 * _inputs_bytes(sizes)
