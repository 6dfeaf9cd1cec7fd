"""The audit of writes on the plain Modbus port: coalesce.py's rule on virtual time (no
socket, no sleep), then a real ModbusSlave with a real pymodbus client in front of a real
trail: a window that closes while the slave runs, and a trail that cannot keep up (its
writer held) neither holding the slave's answers nor losing a count."""

from __future__ import annotations

import asyncio
import struct
import threading
import time
from pathlib import Path
from typing import Any

from pymodbus.client import ModbusTcpClient

from softplc.hmi.coalesce import Coalescer, describe_write
from softplc.hmi.server import ModbusSlave
from softplc.hmi.writeaudit import WriteAudit, WritesAudited
from softplc.security.audit import AuditTrail
from tests.hmi.helpers import ImageSource, run_in_thread
from tests.support import eventually

WHO = {"user": None, "role": "operator", "via": "anonymous"}


def fc6(address: int, value: int) -> dict[str, Any]:
    return describe_write(struct.pack(">BHH", 6, address, value))


def coalescer(**options: Any) -> Coalescer:
    return Coalescer(WHO, {"policy": "open"}, **{"window_s": 10.0, **options})


def test_a_single_write_is_one_record_at_once() -> None:
    rule = coalescer()
    record = rule.note("10.0.0.5", 1, fc6(1028, 42), 0, now_s=0.0)
    assert record == {**WHO, "peer": "10.0.0.5", "iface": "modbus", "action": "write",
                      "outcome": "applied", "status": 0, "detail": {
                          "function": 6, "table": "holding registers", "address": 1028,
                          "values": [42], "unit": 1, "policy": "open", "writes": 1}}
    assert rule.due(10.0, 1_700_000_000.0) == []  # nothing more happened: nothing more
    assert rule.open == 0


def test_a_setpoint_written_20_times_a_second_is_one_record_per_window() -> None:
    rule = coalescer()
    records = []
    for n in range(20 * 35):  # 35 s at 20 Hz, the value changing every second
        now_s = n / 20
        if (record := rule.note("10.0.0.5", 1, fc6(1028, n // 20), 0, now_s)) is not None:
            records.append(record)
        records += rule.due(now_s, 1_700_000_000.0 + now_s)
    records += rule.drain(35.0, 1_700_000_035.0)
    assert len(records) == 1 + 4  # the first at once, then one per 10 s window (3 + the rest)
    assert sum(r["detail"]["writes"] for r in records) == 700
    last = records[-1]["detail"]
    # The last window: writes 601..699 (30.05 s .. 34.95 s), values 30 .. 34.
    assert last["values"] == [34] and last["writes"] == 99 and last["changed"] == 4
    assert last["first"].startswith("2023-11-14T22:13:50.0")
    assert last["last"].startswith("2023-11-14T22:13:54.9")
    assert rule.open == 0


def test_outcomes_units_and_addresses_are_kept_apart() -> None:
    rule = coalescer()
    first = [rule.note("10.0.0.5", 1, fc6(1028, 1), 0, 0.0),
             rule.note("10.0.0.5", 1, fc6(1028, 1), 2, 0.1),  # refused: its own record
             rule.note("10.0.0.5", 2, fc6(1028, 1), 0, 0.2),
             rule.note("10.0.0.5", 1, fc6(1029, 1), 0, 0.3),
             rule.note("10.0.0.6", 1, fc6(1028, 1), 0, 0.4)]
    assert all(first) and first[1] is not None and first[1]["outcome"] == "refused"
    assert first[1]["status"] == 2
    assert rule.note("10.0.0.5", 1, fc6(1028, 7), 0, 1.0) is None  # counted
    closed = rule.due(10.5, 1_700_000_000.0)
    assert [(r["detail"]["writes"], r["detail"]["values"]) for r in closed] == [(1, [7])]
    assert rule.due(20.5, 1_700_000_000.0) == [] and rule.open == 0


def test_keys_beyond_the_table_are_counted_in_one_record_naming_their_peers() -> None:
    rule = coalescer(max_keys=4, max_keys_per_peer=2)
    immediate = [rule.note("10.0.0.5", 1, fc6(a, 0), 0, 0.0) for a in range(100)]
    assert sum(r is not None for r in immediate) == 2  # that peer's share of the table
    immediate = [rule.note(f"10.0.1.{n}", 1, fc6(0, 0), 0, 0.0) for n in range(20)]
    assert sum(r is not None for r in immediate) == 2  # the rest of the table
    beyond = rule.due(10.0, 1_700_000_000.0)
    assert len(beyond) == 1
    detail = beyond[0]["detail"]
    assert detail["writes"] == 98 + 18 and detail["beyond_keys"] == 4
    assert detail["peers"][:2] == ["10.0.0.5", "10.0.1.2"] and len(detail["peers"]) == 8
    assert detail["more_peers"] == 19 - 8 and beyond[0]["peer"] == "10.0.0.5"


def test_a_lagging_trail_counts_even_first_writes_and_loses_none() -> None:
    rule = coalescer()
    assert rule.note("10.0.0.5", 1, fc6(5, 1), 0, 0.0, record_now=False) is None
    assert rule.note("10.0.0.5", 1, fc6(5, 2), 0, 1.0, record_now=False) is None
    (record,) = rule.drain(2.0, 1_700_000_000.0)
    assert record["detail"]["writes"] == 2 and record["detail"]["values"] == [2]


def test_malformed_writes_are_recorded_by_their_function() -> None:
    rule = coalescer()
    record = rule.note("10.0.0.5", 1, describe_write(bytes([16, 0])), 3, 0.0)
    assert record is not None and record["detail"]["malformed"] is True
    assert record["outcome"] == "refused" and record["status"] == 3


def records(state: Path) -> list[dict[str, Any]]:
    return [r for r in AuditTrail(state).records() if r.get("iface") == "modbus"]


def test_a_real_slave_records_a_burst_as_its_first_write_and_the_windows_count(
        tmp_path: Path) -> None:
    source = ImageSource()
    audit = WritesAudited(AuditTrail(tmp_path), "open", window_s=0.5)
    slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0, audit=audit)
    with run_in_thread(slave) as handle:
        client = ModbusTcpClient("127.0.0.1", port=handle.port, timeout=5, retries=0)
        assert client.connect()
        try:
            assert not client.write_coil(801, True, device_id=1).isError()  # %MX0.1
            assert client.write_register(2048, 5, device_id=1).exception_code == 2  # %MD0
            for n in range(50):
                assert not client.write_register(1028, n, device_id=1).isError()  # %MW4
            # The burst's window closes while the slave serves on: its count is written.
            eventually(lambda: sum(r["detail"]["writes"] for r in records(tmp_path)
                                   if r["detail"].get("iec") == "%MW4") == 50, 10,
                       "the burst's count recorded", show=lambda: records(tmp_path))
        finally:
            client.close()
    written = records(tmp_path)
    coil = [r for r in written if r["detail"].get("iec") == "%MX0.1"]
    assert [(r["outcome"], r["detail"]["values"], r["detail"]["writes"]) for r in coil] == [
        ("applied", [1], 1)]
    refused = [r for r in written if r["detail"].get("iec") == "%MD0"]
    assert [(r["outcome"], r["status"]) for r in refused] == [("refused", 2)]
    burst = [r for r in written if r["detail"].get("iec") == "%MW4"]
    assert burst[0]["detail"]["values"] == [0] and burst[-1]["detail"]["values"] == [49]
    assert all(r["peer"] == "127.0.0.1" and r["role"] == "operator" and r["user"] is None
               for r in written)
    assert AuditTrail(tmp_path).verify().ok


class HeldTrail:
    """An AuditTrail whose appends wait until `release` is set (a trail on a stalled disk)."""

    def __init__(self, state: Path) -> None:
        self.trail = AuditTrail(state)
        self.release = threading.Event()

    def append(self, entry: dict[str, Any]) -> dict[str, Any]:
        self.release.wait(30)
        return self.trail.append(entry)


def test_a_stalled_trail_never_holds_the_answers_and_loses_no_count(tmp_path: Path) -> None:
    source = ImageSource()
    held = HeldTrail(tmp_path)
    audit = WritesAudited(held, "open", window_s=0.2)
    slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0, audit=audit)
    try:
        with run_in_thread(slave) as handle:
            client = ModbusTcpClient("127.0.0.1", port=handle.port, timeout=5, retries=0)
            assert client.connect()
            try:
                started = time.monotonic()
                for n in range(300):  # distinct registers: a record each, or a count beyond
                    assert not client.write_register(n, n, device_id=1).isError()
                write_s = (time.monotonic() - started) / 300
                # A read (never audited) as the yardstick of this machine's round trip now.
                started = time.monotonic()
                for _ in range(50):
                    assert not client.read_holding_registers(0, count=1, device_id=1).isError()
                read_s = (time.monotonic() - started) / 50
            finally:
                client.close()
            held.release.set()
    finally:
        held.release.set()
    # Held, one record would have cost the 30 s the trail waits.
    assert write_s < max(20 * read_s, 0.05), (write_s, read_s)
    eventually(lambda: sum(r["detail"]["writes"] for r in records(tmp_path)) == 300, 30,
               "every write counted once", show=lambda: len(records(tmp_path)))
    assert AuditTrail(tmp_path).verify().ok


def test_while_the_writer_lags_first_writes_are_counted_not_queued(tmp_path: Path) -> None:
    held = HeldTrail(tmp_path)

    async def burst() -> int:
        audit = WriteAudit(WritesAudited(held, "symbols", window_s=60.0), max_pending=2)
        for n in range(40):
            audit.write("10.0.0.5", 1, struct.pack(">BHH", 6, n % 4, n), b"\x06", 1.0 + n)
        waiting = audit.pending
        held.release.set()
        await audit.close()
        return waiting

    assert asyncio.run(burst()) == 2  # two records waited; the rest became counts
    written = records(tmp_path)
    assert sum(r["detail"]["writes"] for r in written) == 40
    assert len(written) == 2 + 4  # the two at once, then one count per register at stop
    assert {r["detail"]["policy"] for r in written} == {"symbols"}
