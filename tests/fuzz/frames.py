"""Random and mutated Modbus TCP requests from a seeded generator: real function codes
and unknown ones, addresses and quantities at and beyond every table edge and limit,
truncated and padded PDUs, wrong byte counts, random unit and transaction ids."""

from __future__ import annotations

import random
import struct

KNOWN = [1, 2, 3, 4, 5, 6, 15, 16, 23]
UNKNOWN = [0, 7, 8, 17, 20, 22, 24, 43, 0x41, 0x7F, 0x80, 0x81, 0x83, 0xFF]
# Table sizes for the default image: coils 1600, discrete inputs 800, input registers
# 1024 + 18 status, holding registers 2048; and the 16-bit edge.
ADDRESSES = [0, 1, 7, 798, 799, 800, 1023, 1024, 1040, 1041, 1042, 1043, 1044, 1599, 1600, 2047,
             2048, 0xFFFE, 0xFFFF]
COUNTS = [0, 1, 2, 8, 9, 17, 120, 121, 122, 123, 124, 125, 126, 1968, 1969, 2000, 2001,
          0x7FFF, 0xFFFF]
MAX_PDU = 253


def _pick(rng: random.Random, edges: list[int]) -> int:
    return rng.choice(edges) if rng.random() < 0.7 else rng.randrange(0x10000)


def _noise(rng: random.Random, n: int) -> bytes:
    return bytes(rng.randrange(256) for _ in range(n))


def _body(rng: random.Random, fc: int) -> bytes:
    address, count = _pick(rng, ADDRESSES), _pick(rng, COUNTS)
    if fc in (1, 2, 3, 4):
        return struct.pack(">HH", address, count)
    if fc == 5:
        value = rng.choice([0xFF00, 0x0000, 0x0001, 0x00FF, 0xFFFF, rng.randrange(0x10000)])
        return struct.pack(">HH", address, value)
    if fc == 6:
        return struct.pack(">HH", address, rng.randrange(0x10000))
    if fc == 15:
        n = (count + 7) // 8
        return struct.pack(">HHB", address, count, n & 0xFF) + _noise(rng, min(n, 240))
    if fc == 16:
        n = 2 * count
        return struct.pack(">HHB", address, count, n & 0xFF) + _noise(rng, min(n, 240))
    if fc == 23:
        w_count = _pick(rng, COUNTS)
        n = 2 * w_count
        return struct.pack(">HHHHB", address, count, _pick(rng, ADDRESSES), w_count,
                           n & 0xFF) + _noise(rng, min(n, 240))
    return _noise(rng, rng.choice([0, 1, 4, 5, 9, 30]))


def _mutate(rng: random.Random, pdu: bytes) -> bytes:
    kind = rng.randrange(5)
    if kind == 0 and len(pdu) > 1:  # truncated PDU
        return pdu[: rng.randrange(1, len(pdu))]
    if kind == 1:  # trailing bytes
        return pdu + _noise(rng, rng.randrange(1, 8))
    if kind == 2 and len(pdu) > 5:  # byte count off by a little
        i = 5 if pdu[0] in (15, 16) else (9 if pdu[0] == 23 and len(pdu) > 9 else 1)
        return pdu[:i] + bytes([(pdu[i] + rng.choice([-1, 1, 2, 128])) & 0xFF]) + pdu[i + 1:]
    if kind == 3:  # one byte flipped anywhere after the function code
        i = rng.randrange(len(pdu))
        return pdu[:i] + bytes([pdu[i] ^ (1 << rng.randrange(8))]) + pdu[i + 1:] if i else pdu
    return pdu


def random_pdu(rng: random.Random) -> bytes:
    fc = rng.choice(KNOWN) if rng.random() < 0.8 else rng.choice([*UNKNOWN, rng.randrange(256)])
    pdu = bytes([fc]) + _body(rng, fc)
    if rng.random() < 0.4:
        pdu = _mutate(rng, pdu)
    return pdu[:MAX_PDU] or bytes([fc])


def mbap(pdu: bytes, tid: int, unit: int, pid: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1, unit) + pdu


def broken_stream(rng: random.Random) -> bytes:
    """Bytes that are not a sequence of ADUs: impossible MBAP lengths, a length that
    disagrees with what follows, random garbage, a header cut short."""
    pdu = random_pdu(rng)
    kind = rng.randrange(5)
    if kind == 0:
        length = rng.choice([0, 1, 255, 256, 0x7FFF, 0xFFFF])
        return struct.pack(">HHHB", 1, 0, length, 1) + pdu
    if kind == 1:  # length says fewer bytes than sent: the rest reads as the next header
        return struct.pack(">HHHB", 1, 0, max(2, len(pdu) - rng.randrange(1, 4)), 1) + pdu
    if kind == 2:  # length says more: the server waits for bytes that never come
        return struct.pack(">HHHB", 1, 0, min(254, len(pdu) + 1 + rng.randrange(1, 40)), 1) + pdu
    if kind == 3:
        return _noise(rng, rng.randrange(1, 600))
    return mbap(pdu, 1, 1)[: rng.randrange(1, 7)]
