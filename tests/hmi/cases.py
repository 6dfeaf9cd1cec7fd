"""Request PDUs and their exact replies, for the image of the `source` fixture (conftest):
%QX 0, 3, 799 and %MX 1, 799 set; %IX 2, 15, 799 set; %IW[i] = i; %QW[i] = 1000 + i;
%MW[i] = 5000 + i; status scan_count 1. Used in-process (test_frames) and over a socket
(test_server)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from softplc.core.image import parse_address
from softplc.core.snapshot import HmiWrite
from softplc.hmi.map import STATUS_WORDS

COILS_SET = {0, 3, 799, 801, 1599}
DI_SET = {2, 15, 799}


@dataclass(frozen=True)
class Case:
    id: str
    pdu: bytes
    reply: bytes
    writes: tuple[HmiWrite, ...] = ()


def pdu(fc: int, fmt: str = "", *fields: int, data: bytes = b"") -> bytes:
    return bytes([fc]) + struct.pack(">" + fmt, *fields) + data


def exc(fc: int, code: int) -> bytes:
    return bytes([fc | 0x80, code])


def bit_bytes(bits: list[int]) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes([len(out)]) + bytes(out)


def reg_bytes(values: list[int]) -> bytes:
    return bytes([2 * len(values)]) + struct.pack(f">{len(values)}H", *values)


def coils(address: int, count: int) -> list[int]:
    return [int(a in COILS_SET) for a in range(address, address + count)]


def holding(address: int, count: int) -> list[int]:
    return [
        (1000 + a if a < 1024 else 5000 + a - 1024) & 0xFFFF
        for a in range(address, address + count)
    ]


def w(iec: str, *values: int) -> HmiWrite:
    return HmiWrite(parse_address(iec), tuple(values))


VALID = [
    Case("fc1-8", pdu(1, "HH", 0, 8), pdu(1) + bit_bytes(coils(0, 8))),
    Case("fc1-qx-mx", pdu(1, "HH", 798, 4), pdu(1) + bit_bytes([0, 1, 0, 1])),
    Case("fc1-all", pdu(1, "HH", 0, 1600), pdu(1) + bit_bytes(coils(0, 1600))),
    Case("fc2-16", pdu(2, "HH", 0, 16), pdu(2) + bytes([2, 0x04, 0x80])),
    Case(
        "fc2-all", pdu(2, "HH", 0, 800), pdu(2) + bit_bytes([int(a in DI_SET) for a in range(800)])
    ),
    Case("fc3-qw-mw", pdu(3, "HH", 1023, 2), pdu(3) + reg_bytes([2023, 5000])),
    Case("fc3-125", pdu(3, "HH", 1923, 125), pdu(3) + reg_bytes(holding(1923, 125))),
    Case("fc4-iw", pdu(4, "HH", 0, 3), pdu(4) + reg_bytes([0, 1, 2])),
    Case("fc4-status", pdu(4, "HH", 1023, 5), pdu(4) + reg_bytes([1023, 0, 0, 0, 1])),
    Case("fc5-on", pdu(5, "HH", 5, 0xFF00), pdu(5, "HH", 5, 0xFF00), (w("%QX0.5", 1),)),
    Case("fc5-off-mx", pdu(5, "HH", 800, 0), pdu(5, "HH", 800, 0), (w("%MX0.0", 0),)),
    Case("fc6", pdu(6, "HH", 1024, 0x1234), pdu(6, "HH", 1024, 0x1234), (w("%MW0", 0x1234),)),
    Case(
        "fc15-across",
        pdu(15, "HHB", 799, 3, 1, data=b"\x05"),
        pdu(15, "HH", 799, 3),
        (w("%QX99.7", 1), w("%MX0.0", 0, 1)),
    ),
    Case(
        "fc15-only-addressed",
        pdu(15, "HHB", 10, 3, 1, data=b"\xff"),
        pdu(15, "HH", 10, 3),
        (w("%QX1.2", 1, 1, 1),),
    ),
    Case(
        "fc16-across",
        pdu(16, "HHB", 1023, 2, 4, data=b"\x00\x01\xff\xff"),
        pdu(16, "HH", 1023, 2),
        (w("%QW1023", 1), w("%MW0", 0xFFFF)),
    ),
    Case(
        "fc16-123",
        pdu(16, "HHB", 0, 123, 246, data=bytes(246)),
        pdu(16, "HH", 0, 123),
        (w("%QW0", *[0] * 123),),
    ),
    Case(
        "fc23",
        pdu(23, "HHHHB", 0, 2, 16, 1, 2, data=b"\xab\xcd"),
        pdu(23) + reg_bytes([1000, 1001]),
        (w("%QW16", 0xABCD),),
    ),
    Case(
        "fc23-reads-before-its-write",
        pdu(23, "HHHHB", 16, 1, 16, 1, 2, data=b"\x00\x07"),
        pdu(23) + reg_bytes([1016]),
        (w("%QW16", 7),),
    ),
    Case(
        "fc23-max",
        pdu(23, "HHHHB", 0, 125, 1024, 121, 242, data=bytes(242)),
        pdu(23) + reg_bytes(holding(0, 125)),
        (w("%MW0", *[0] * 121),),
    ),
]

ILLEGAL_FUNCTION = [
    Case(f"fc{fc:#04x}", bytes([fc]) + rest, exc(fc, 1))
    for fc, rest in [
        (0, b""),
        (7, b""),
        (8, b"\x00\x00\x12\x34"),
        (17, b""),
        (20, b"\x07\x06\x00\x01\x00\x00\x00\x01"),
        (22, b"\x00\x00\xff\xff\x00\x00"),
        (24, b"\x00\x00"),
        (43, b"\x0e\x01\x00"),
        (0x41, b"\x00"),
        (0x81, b"\x02"),
        (0x83, b"\x00\x00\x00\x01"),
        (0xFF, b""),
    ]
]

ILLEGAL_VALUE = [
    Case(id_, req, exc(req[0], 3))
    for id_, req in [
        ("fc1-qty0", pdu(1, "HH", 0, 0)),
        ("fc1-qty2001", pdu(1, "HH", 0, 2001)),
        ("fc1-qty2001-before-address", pdu(1, "HH", 0xFFFF, 2001)),
        ("fc1-truncated", pdu(1, "HB", 0, 0)),
        ("fc1-trailing-byte", pdu(1, "HHB", 0, 1, 0)),
        ("fc2-qty0", pdu(2, "HH", 0, 0)),
        ("fc2-qty2001", pdu(2, "HH", 0, 2001)),
        ("fc3-qty0", pdu(3, "HH", 0, 0)),
        ("fc3-qty126", pdu(3, "HH", 0, 126)),
        ("fc3-qty126-before-address", pdu(3, "HH", 5000, 126)),
        ("fc3-truncated", pdu(3)),
        ("fc4-qty0", pdu(4, "HH", 0, 0)),
        ("fc4-qty126", pdu(4, "HH", 0, 126)),
        ("fc5-value-1234", pdu(5, "HH", 0, 0x1234)),
        ("fc5-value-00ff", pdu(5, "HH", 0, 0x00FF)),
        ("fc5-value-0001", pdu(5, "HH", 0, 1)),
        ("fc5-value-before-address", pdu(5, "HH", 5000, 0x1234)),
        ("fc5-truncated", pdu(5, "H", 0)),
        ("fc6-truncated", pdu(6, "HB", 0, 1)),
        ("fc15-qty0", pdu(15, "HHB", 0, 0, 0)),
        ("fc15-qty1969", pdu(15, "HHB", 0, 1969, 247, data=bytes(247))),
        ("fc15-qty1969-before-address", pdu(15, "HHB", 5000, 1969, 247, data=bytes(247))),
        ("fc15-byte-count-vs-qty", pdu(15, "HHB", 0, 8, 2, data=b"\x00\x00")),
        ("fc15-byte-count-vs-data", pdu(15, "HHB", 0, 16, 2, data=b"\x00")),
        ("fc15-no-byte-count", pdu(15, "HH", 0, 1)),
        ("fc16-qty0", pdu(16, "HHB", 0, 0, 0)),
        ("fc16-qty124", pdu(16, "HHB", 0, 124, 0)),
        ("fc16-byte-count-vs-qty", pdu(16, "HHB", 0, 2, 3, data=b"\x00\x00\x00")),
        ("fc16-byte-count-vs-data", pdu(16, "HHB", 0, 2, 4, data=b"\x00\x00")),
        ("fc16-byte-count-bad-before-address", pdu(16, "HHB", 5000, 1, 3, data=b"\x00\x00\x00")),
        ("fc23-read-qty0", pdu(23, "HHHHB", 0, 0, 0, 1, 2, data=b"\x00\x00")),
        ("fc23-read-qty126", pdu(23, "HHHHB", 0, 126, 0, 1, 2, data=b"\x00\x00")),
        ("fc23-write-qty0", pdu(23, "HHHHB", 0, 1, 0, 0, 0)),
        ("fc23-write-qty122", pdu(23, "HHHHB", 0, 1, 0, 122, 0)),
        ("fc23-byte-count-vs-qty", pdu(23, "HHHHB", 0, 1, 0, 1, 4, data=bytes(4))),
        ("fc23-byte-count-vs-data", pdu(23, "HHHHB", 0, 1, 0, 2, 4, data=bytes(2))),
        ("fc23-truncated", pdu(23, "HHH", 0, 1, 0)),
    ]
]

# Ends of the register tables with the default sizes (docs/modbus.md): %QL ends the holding
# registers at 10 * 1024 + 4 * 256, %IL the input registers at 4 * 1024 + 4 * 256.
HR_END, IR_END = 11264, 5120

ILLEGAL_ADDRESS = [
    Case(id_, req, exc(req[0], 2))
    for id_, req in [
        ("fc1-start-beyond", pdu(1, "HH", 1600, 1)),
        ("fc1-end-beyond", pdu(1, "HH", 1599, 2)),
        ("fc1-qty2000-beyond-map", pdu(1, "HH", 0, 2000)),
        ("fc1-last-address", pdu(1, "HH", 0xFFFF, 1)),
        ("fc2-start-beyond", pdu(2, "HH", 800, 1)),
        ("fc2-end-beyond", pdu(2, "HH", 0, 801)),
        ("fc3-start-beyond", pdu(3, "HH", HR_END, 1)),
        ("fc3-end-beyond", pdu(3, "HH", HR_END - 8, 9)),
        ("fc3-gap-after-md", pdu(3, "HH", 2048 + 512, 1)),
        ("fc3-across-the-gap", pdu(3, "HH", 2048 + 510, 4)),
        ("fc3-wraps-16-bits", pdu(3, "HH", 0xFFFF, 2)),
        ("fc4-start-beyond", pdu(4, "HH", IR_END, 1)),
        ("fc4-gap-after-status", pdu(4, "HH", 1024 + STATUS_WORDS, 1)),
        ("fc4-end-beyond-status", pdu(4, "HH", 1024 + STATUS_WORDS - 2, 3)),
        ("fc5-beyond", pdu(5, "HH", 1600, 0xFF00)),
        ("fc6-beyond", pdu(6, "HH", HR_END, 1)),
        ("fc6-half-an-md", pdu(6, "HH", 2048, 1)),
        ("fc15-start-beyond", pdu(15, "HHB", 1600, 1, 1, data=b"\x01")),
        ("fc15-end-beyond", pdu(15, "HHB", 1599, 2, 1, data=b"\x03")),
        ("fc15-qty1968-beyond-map", pdu(15, "HHB", 0, 1968, 246, data=bytes(246))),
        ("fc16-start-beyond", pdu(16, "HHB", HR_END, 1, 2, data=b"\x00\x01")),
        ("fc16-end-beyond", pdu(16, "HHB", HR_END - 1, 2, 4, data=bytes(4))),
        ("fc16-half-an-ml", pdu(16, "HHB", 4096 + 1, 4, 8, data=bytes(8))),
        ("fc16-mw-and-half-an-md", pdu(16, "HHB", 2047, 2, 4, data=bytes(4))),
        ("fc23-read-beyond", pdu(23, "HHHHB", HR_END, 1, 0, 1, 2, data=b"\x00\x01")),
        ("fc23-write-beyond", pdu(23, "HHHHB", 0, 1, HR_END - 1, 2, 4, data=bytes(4))),
    ]
]

ALL = VALID + ILLEGAL_FUNCTION + ILLEGAL_VALUE + ILLEGAL_ADDRESS
