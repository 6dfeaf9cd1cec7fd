"""softplc's Sparkplug B codec against Eclipse Tahu JS (an implementation nobody here wrote),
both ways: what softplc encodes for every datatype it sends (negative small ints sign-extended,
properties, null) and what a host encodes in an NCMD; malformed payloads are a DecodeError;
the URL's errors name what is wrong."""

from __future__ import annotations

import math

import pytest

from softplc.sparkplug import codec
from softplc.sparkplug.codec import DecodeError, Metric, Payload
from softplc.sparkplug.config import parse_url
from tests.sparkplug.conftest import Tahu

SENT = [  # (datatype, value, Tahu's type name, the value Tahu gives)
    (codec.BOOLEAN, True, "Boolean", True), (codec.INT16, -5, "Int16", -5),
    (codec.INT16, 32767, "Int16", 32767), (codec.UINT16, 65535, "UInt16", 65535),
    (codec.INT32, -2147483648, "Int32", -2147483648), (codec.FLOAT, 21.5, "Float", 21.5),
    (codec.DOUBLE, -1e300, "Double", -1e300), (codec.STRING, "RUNNING", "String", "RUNNING"),
    (codec.INT64, 255, "Int64", "255"), (codec.UINT64, 2**40, "UInt64", str(2**40)),
]


def test_what_softplc_encodes_tahu_decodes(tahu: Tahu) -> None:
    metrics = tuple(Metric(f"m{i}", dt, v, alias=i + 1, timestamp=1700000000000 + i)
                    for i, (dt, v, _, _) in enumerate(SENT))
    props = (("readOnly", codec.BOOLEAN, True), ("engUnit", codec.STRING, "°C"),
             ("engLow", codec.DOUBLE, -50.0), ("engHigh", codec.DOUBLE, 150.0))
    extra = (Metric("scaled", codec.DOUBLE, 4.25, 99, 1, props),
             Metric("nothing", codec.STRING, None, 100, 1))
    decoded = tahu.decode([codec.encode(Payload(1700000000000, metrics + extra, 7))])[0]
    payload = decoded["payload"]
    assert int(payload["seq"]) == 7 and int(payload["timestamp"]) == 1700000000000
    got = {m["name"]: m for m in payload["metrics"]}
    for i, (_, _, type_name, value) in enumerate(SENT):
        metric = got[f"m{i}"]
        assert (metric["type"], metric["value"], int(metric["alias"])) == (type_name, value,
                                                                           i + 1)
    assert {k: (v["type"], v["value"]) for k, v in got["scaled"]["properties"].items()} == {
        "readOnly": ("Boolean", True), "engUnit": ("String", "°C"),
        "engLow": ("Double", -50.0), "engHigh": ("Double", 150.0)}
    assert got["nothing"]["value"] is None
    # DATA by alias: no name and no datatype on the wire, the value in its datatype's field
    data = codec.encode(Payload(5, (Metric(None, codec.INT16, -5, 2, 5, typed=False),), 8))
    raw = tahu.decode([data])[0]["raw"]["metrics"][0]
    assert raw == {"alias": "2", "timestamp": "5", "intValue": 4294967291}


def test_what_tahu_encodes_softplc_decodes(tahu: Tahu) -> None:
    data = tahu.encode({"timestamp": 1700000000000, "metrics": [
        {"name": "Node Control/Rebirth", "type": "Boolean", "value": True},
        {"name": "i16", "type": "Int16", "value": -300},
        {"name": "i32", "type": "Int32", "value": -7},
        {"name": "u32", "type": "UInt32", "value": 4000000000},
        {"name": "f", "type": "Float", "value": 0.1},
        {"name": "d", "type": "Double", "value": math.pi},
        {"name": "s", "type": "String", "value": "start"},
        {"alias": 12, "type": "Int16", "value": -1}]})
    payload = codec.decode(data)
    got = {m.name if m.name else m.alias: m.value for m in payload.metrics}
    assert got["Node Control/Rebirth"] is True and got["i16"] == -300 and got["i32"] == -7
    assert got["u32"] == 4000000000  # Tahu JS sends UInt32 in long_value: read either
    assert got["f"] == pytest.approx(0.1, rel=1e-7) and got["d"] == math.pi
    assert got["s"] == "start" and got[12] == -1
    assert payload.timestamp == 1700000000000


@pytest.mark.parametrize("data", [b"\x0a\xff", b"\x12\x05\x0a", b"\x08", b"\x00\x01",
                                  b"\x12\x03\x0a\x01\xff", b"\x0b"])
def test_malformed_payloads_are_decode_errors(data: bytes) -> None:
    with pytest.raises(DecodeError):
        codec.decode(data)


@pytest.mark.parametrize(("url", "says"), [
    ("http://h:1/g/n", "scheme must be mqtt"), ("mqtt://h/g/n", "HOST:PORT is missing"),
    ("mqtt://h:x/g/n", "port is not a number"), ("mqtt://h:1/g", "/GROUP/EDGE_NODE"),
    ("mqtt://h:1/g/n/d", "/GROUP/EDGE_NODE"), ("mqtt://h:1/g+/n", "holds + / or #"),
    ("mqtt://h:1/g/n?x=1", "no query")])
def test_bad_urls_say_what_is_wrong(url: str, says: str) -> None:
    with pytest.raises(ValueError, match=says.replace("+", r"\+")):
        parse_url(url)


def test_a_url_with_user_and_password_keeps_them_out_of_repr() -> None:
    config = parse_url("mqtts://op%40plant:s%3Acret@broker.local:8883/Plant%201/tank1")
    assert (config.user, config.password, config.host, config.port) == (
        "op@plant", "s:cret", "broker.local", 8883)
    assert (config.group, config.node, config.tls) == ("Plant 1", "tank1", True)
    assert "cret" not in repr(config)
