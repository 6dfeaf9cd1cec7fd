"""The Modbus application layer, in-process: PDUs and ADUs in, replies out, no sockets."""

from __future__ import annotations

import pytest

from softplc.core.image import Area, parse_address
from softplc.core.snapshot import HmiWrite
from softplc.hmi.frames import (
    Adu,
    FramingError,
    Responder,
    encode_adu,
    split_adu,
)
from softplc.hmi.map import RegisterMap, Writable
from tests.hmi import cases
from tests.hmi.cases import Case
from tests.hmi.helpers import ImageSource, adu


def responder(
    source: ImageSource, writable: Writable | None = None, read_only: bool = False
) -> Responder:
    register_map = RegisterMap(source.image.sizes, writable=writable, read_only=read_only)
    return Responder(register_map, source, source.sink)


@pytest.mark.parametrize("case", cases.ALL, ids=lambda c: c.id)
def test_request_reply_and_journal(source: ImageSource, case: Case) -> None:
    assert responder(source).answer_pdu(case.pdu) == case.reply
    assert tuple(source.writes) == case.writes


def test_supported_function_codes(source: ImageSource) -> None:
    assert sorted(responder(source).function_codes) == [1, 2, 3, 4, 5, 6, 15, 16, 23]


def test_writes_are_not_visible_before_the_next_snapshot(source: ImageSource) -> None:
    r = responder(source)
    assert r.answer_pdu(bytes.fromhex("0600050007")) == bytes.fromhex("0600050007")
    assert r.answer_pdu(bytes.fromhex("0300050001")) == bytes.fromhex("0302") + (1005).to_bytes(2)
    source.publish()
    assert r.answer_pdu(bytes.fromhex("0300050001")) == bytes.fromhex("03020007")


def test_writable_refusal_is_02_and_journals_nothing(source: ImageSource) -> None:
    r = responder(source, writable=lambda a: a.area is Area.MEMORY)
    assert r.answer_pdu(bytes.fromhex("0f031f000301 05")) == bytes.fromhex("8f02")
    assert r.answer_pdu(bytes.fromhex("10 03ff 0002 04 00010002")) == bytes.fromhex("9002")
    assert r.answer_pdu(bytes.fromhex("17 0000 0001 0000 0001 02 0001")) == bytes.fromhex("9702")
    assert source.writes == []
    assert r.answer_pdu(bytes.fromhex("0603ff0001"))[0] == 0x86
    assert r.answer_pdu(bytes.fromhex("0604000001")) == bytes.fromhex("0604000001")
    assert source.writes == [HmiWrite(parse_address("%MW0"), (1,))]


def test_read_only_refuses_writes_but_still_validates_quantity_first(source: ImageSource) -> None:
    r = responder(source, read_only=True)
    assert r.answer_pdu(bytes.fromhex("050000ff00")) == bytes.fromhex("8502")
    assert r.answer_pdu(bytes.fromhex("0500001234")) == bytes.fromhex("8503")
    assert r.answer_pdu(bytes.fromhex("1000000000 00")) == bytes.fromhex("9003")
    assert source.writes == []


def test_answer_echoes_tid_and_unit_and_drops_foreign_protocol(source: ImageSource) -> None:
    r = responder(source)
    reply = r.answer(Adu(0xBEEF, 0, 0xF7, bytes.fromhex("0400000001")))
    assert reply == encode_adu(0xBEEF, 0xF7, bytes.fromhex("04020000"))
    assert reply is not None and reply[:7] == bytes.fromhex("beef00000005f7")
    assert r.answer(Adu(1, 1, 1, bytes.fromhex("0400000001"))) is None


def test_split_adu_waits_for_whole_frames_and_walks_a_pipeline() -> None:
    two = adu(b"\x03\x00\x00\x00\x01", tid=1) + adu(b"\x04\x00\x00\x00\x01", tid=2)
    for cut in range(12):  # a partial first frame
        assert split_adu(two[:cut]) == (None, 0)
    first, end = split_adu(two)
    assert first == Adu(1, 0, 1, b"\x03\x00\x00\x00\x01") and end == 12
    second, end2 = split_adu(two, end)
    assert second is not None and second.transaction_id == 2 and end2 == len(two)
    assert split_adu(two, end2) == (None, end2)


# Written out, not from the constants: a bound that moves with its constant tests nothing.
@pytest.mark.parametrize("length", [0, 1, 255, 0xFFFF])
def test_split_adu_rejects_impossible_lengths(length: int) -> None:
    with pytest.raises(FramingError, match=f"MBAP length {length} is not in 2..254"):
        split_adu(b"\x00\x01\x00\x00" + length.to_bytes(2, "big") + b"\x01\x03")


def test_the_smallest_legal_frame_unit_id_and_function_code_is_answered(
        source: ImageSource) -> None:
    """MBAP length 2: a unit id and a function code, no data. A gateway may send it; the
    slave answers it with an exception (03: the request's data is missing), never a close."""
    frame = bytes.fromhex("0007 0000 0002 11 03")
    request, end = split_adu(frame + frame)
    assert request == Adu(7, 0, 0x11, b"\x03") and end == 8
    assert split_adu(frame + frame, end) == (request, 16)
    r = responder(source)
    assert r.answer(request) == bytes.fromhex("0007 0000 0003 11 8303")
    assert r.answer(Adu(8, 0, 1, b"\x2b")) == bytes.fromhex("0008 0000 0003 01 ab01")


def test_the_largest_legal_frame_253_bytes_of_pdu_is_split() -> None:
    """MBAP length 254: a unit id and a PDU of 253 bytes (ADU 260 bytes, the spec's bound)."""
    pdu = bytes([0x10]) + bytes(252)
    frame = bytes.fromhex("0001 0000 00fe 01") + pdu
    assert len(frame) == 260
    assert split_adu(frame) == (Adu(1, 0, 1, pdu), 260)
    assert split_adu(frame[:-1]) == (None, 0)  # one byte short: wait for it
