"""A full HMI write queue on the real channel (runtime/shared/channel.py, nobody draining it, as
when the scan process is overloaded or gone): the Modbus slave answers exception 06 (busy, retry)
to every write, logs one line without a traceback, and reads go on (issue 39 item 4). The
slave on 127.0.0.1 port 0, a pymodbus client; the queue filled by the channel's own sender."""

from __future__ import annotations

import logging

import pytest
from pymodbus.client import ModbusTcpClient

from softplc.core.image import parse_address
from softplc.core.snapshot import ChannelFull, HmiWrite
from softplc.hmi.server import ModbusSlave
from softplc.runtime.shared.channel import Channel
from tests.hmi.helpers import ImageSource, run_in_thread


def test_a_full_channel_answers_06_without_a_traceback(
        source: ImageSource, caplog: pytest.LogCaptureFixture) -> None:
    channel = Channel()
    with pytest.raises(ChannelFull):  # the kernel pipe holds a few hundred writes
        for _ in range(100_000):
            channel.send_hmi_write(HmiWrite(parse_address("%MW3"), (1,)))
    slave = ModbusSlave(source, channel.send_hmi_write, sizes=source.image.sizes, port=0)
    with caplog.at_level(logging.DEBUG, logger="softplc"), run_in_thread(slave) as handle:
        c = ModbusTcpClient("127.0.0.1", port=handle.port, timeout=3, retries=0)
        assert c.connect()
        try:
            answers = [c.write_register(0, 1), c.write_coil(5, True),
                       c.write_registers(2, [1, 2]), c.write_coils(0, [True, False])]
            assert [getattr(a, "exception_code", None) for a in answers] == [6] * 4
            assert not c.read_input_registers(0, count=1).isError()
        finally:
            c.close()
    logged = [r for r in caplog.records if r.levelno >= logging.INFO]
    assert [r.exc_info for r in logged] == [None] * len(logged)
    assert any("06 (busy)" in r.getMessage() for r in logged), [r.getMessage() for r in logged]
    commands, hmi = channel.drain()
    assert commands == [] and all(w.values == (1,) for w in hmi)  # none of the refused writes
