"""The command/HMI channel: in one process, and across real spawned and forked processes."""

from __future__ import annotations

import multiprocessing as mp
import queue
import threading
from collections.abc import Iterator
from multiprocessing.context import BaseContext
from multiprocessing.synchronize import Event
from typing import Any

import pytest

from softplc.core.image import parse_address
from softplc.core.lifecycle import Command, PlcState
from softplc.core.snapshot import ChannelFull, CommandReply, CommandRequest, HmiWrite
from softplc.runtime.shared.channel import Channel

MW3 = parse_address("%MW3")
MX0 = parse_address("%MX0.0")


def _echo(request: CommandRequest) -> CommandReply:
    text = request.program_text or ""
    return CommandReply(
        request.id, True, f"{request.command.value} {request.id} {len(text)}", PlcState.STOPPED
    )


def _scan_main(channel: Channel, writes: Any, stop: Event) -> None:
    """A stand-in scan process: drain, answer every command, report every HMI write."""
    for _ in range(60_000):  # bounded: about a minute at 1 ms per scan
        if stop.wait(0.001):
            return
        commands, hmi = channel.drain()
        for write in hmi:
            writes.put(write)
        for request in commands:
            channel.reply(_echo(request))


@pytest.fixture(params=["spawn", "fork"])
def scan(request: pytest.FixtureRequest) -> Iterator[tuple[Channel, Any, BaseContext]]:
    ctx = mp.get_context(request.param)
    channel = Channel(ctx=ctx)
    writes = ctx.Queue()
    stop = ctx.Event()
    child = ctx.Process(target=_scan_main, args=(channel, writes, stop))
    child.start()
    yield channel, writes, ctx
    stop.set()
    child.join(timeout=30)
    assert child.exitcode == 0


def test_command_and_reply_across_processes(scan: tuple[Channel, Any, BaseContext]) -> None:
    channel, _, _ = scan
    reply = channel.send_command(CommandRequest(1, Command.START), timeout_s=30)
    assert reply == CommandReply(1, True, "start 1 0", PlcState.STOPPED)


def test_a_large_download_arrives_whole(scan: tuple[Channel, Any, BaseContext]) -> None:
    channel, _, _ = scan
    text = "places: [é, ü, 漢]\n" * 20_000  # ~ 0.4 MB of UTF-8: many frames, several scans
    request = CommandRequest(7, Command.DOWNLOAD, program_text=text, program_path="p.yaml")
    reply = channel.send_command(request, timeout_s=30)
    assert reply.message == f"download 7 {len(text)}"


def test_hmi_writes_arrive_in_order(scan: tuple[Channel, Any, BaseContext]) -> None:
    channel, writes, _ = scan
    sent = [HmiWrite(MW3, (i, 65535 - i)) for i in range(300)]
    sent.append(HmiWrite(MX0, tuple(i % 2 for i in range(1968))))  # FC15's maximum
    for write in sent:
        channel.send_hmi_write(write)
    got = [writes.get(timeout=30) for _ in sent]
    assert got == sent


def test_concurrent_client_threads_get_their_own_replies(
    scan: tuple[Channel, Any, BaseContext],
) -> None:
    channel, _, _ = scan
    errors: list[str] = []

    def client(base: int) -> None:
        for i in range(base, base + 15):
            text = "x" * (i % 3) * 3000  # some single-frame, some multi-frame
            reply = channel.send_command(
                CommandRequest(i, Command.DOWNLOAD, program_text=text), timeout_s=30
            )
            if reply.message != f"download {i} {len(text)}":
                errors.append(f"request {i} got {reply}")

    threads = [threading.Thread(target=client, args=(100 * k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors


def _client_main(channel: Channel, base: int, results: Any) -> None:
    for i in range(base, base + 20):
        reply = channel.send_command(CommandRequest(i, Command.STOP), timeout_s=30)
        results.put(reply.message == f"stop {i} 0")


def test_several_client_processes_and_a_dead_ones_lane(
    scan: tuple[Channel, Any, BaseContext],
) -> None:
    channel, _, ctx = scan
    results = ctx.Queue()
    clients = [
        ctx.Process(target=_client_main, args=(channel, 1000 * k, results)) for k in (1, 2, 3)
    ]
    for c in clients:
        c.start()
    _client_main(channel, 0, results)  # this process too, at the same time
    for c in clients:
        c.join(timeout=60)
        assert c.exitcode == 0
    assert all(results.get(timeout=30) for _ in range(80))
    # 4 lanes, all claimed once; dead clients' lanes are reclaimed by new processes.
    late = [
        ctx.Process(target=_client_main, args=(channel, 9000 + 100 * k, results)) for k in (0, 1)
    ]
    for c in late:
        c.start()
    for c in late:
        c.join(timeout=60)
        assert c.exitcode == 0
    assert all(results.get(timeout=30) for _ in range(40))


def test_timeout_when_nobody_drains() -> None:
    channel = Channel()
    with pytest.raises(TimeoutError, match=r"no reply to command stop \(id 5\) within 0.1 s"):
        channel.send_command(CommandRequest(5, Command.STOP), timeout_s=0.1)


def test_a_command_that_cannot_be_queued_times_out() -> None:
    channel = Channel()
    big = CommandRequest(6, Command.DOWNLOAD, program_text="y" * 200_000)  # > the pipe
    with pytest.raises(TimeoutError, match="could not be queued"):
        channel.send_command(big, timeout_s=0.1)


def test_a_full_hmi_queue_refuses_instead_of_blocking() -> None:
    channel = Channel()
    accepted = 0
    with pytest.raises(ChannelFull, match=r"%MW3 refused"):
        for _ in range(100_000):
            channel.send_hmi_write(HmiWrite(MW3, (1,)))
            accepted += 1
    assert accepted > 100  # the kernel pipe holds a few hundred writes
    commands, hmi = channel.drain()
    assert commands == [] and len(hmi) == channel.drain_limit  # bounded per drain
    channel.send_hmi_write(HmiWrite(MW3, (2,)))  # room again


def test_drain_is_bounded_and_keeps_order_across_calls() -> None:
    channel = Channel(drain_limit=10)
    for i in range(25):
        channel.send_hmi_write(HmiWrite(MW3, (i,)))
    batches = [channel.drain()[1] for _ in range(4)]
    assert [len(b) for b in batches] == [10, 10, 5, 0]
    assert [w.values[0] for b in batches for w in b] == list(range(25))


def test_bad_hmi_values_are_refused_before_queueing() -> None:
    channel = Channel()
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        channel.send_hmi_write(HmiWrite(MW3, (70_000,)))
    with pytest.raises(ValueError, match="too long"):
        channel.send_hmi_write(HmiWrite(MW3, tuple(range(300, 3300))))
    assert channel.drain() == ([], [])


def test_in_process_round_trip_and_reply_rules() -> None:
    channel = Channel()
    replies: queue.Queue[CommandReply] = queue.Queue()
    sender = threading.Thread(
        target=lambda: replies.put(channel.send_command(CommandRequest(3, Command.KILL), 30))
    )
    sender.start()
    commands: list[CommandRequest] = []
    for _ in range(10_000):
        commands = channel.drain()[0]
        if commands:
            break
        sender.join(timeout=0.001)
    assert commands == [CommandRequest(3, Command.KILL)]
    with pytest.raises(ValueError, match="no drained command with id 4"):
        channel.reply(CommandReply(4, True, "", PlcState.KILLED))
    channel.reply(CommandReply(3, True, "killed", PlcState.KILLED))
    sender.join(timeout=30)
    assert replies.get_nowait() == CommandReply(3, True, "killed", PlcState.KILLED)
    with pytest.raises(ValueError, match="id 3"):
        channel.reply(CommandReply(3, True, "twice", PlcState.KILLED))


def test_a_spent_budget_drains_one_frame_a_call_and_the_command_arrives_whole() -> None:
    """A download's frames are taken while the scan's drain budget lasts, one at least: with
    none left after the first, a 40 KB program needs one drain per frame (the scan reads
    ~60 us a frame; 16, a full pipe, took 1.3 ms of a 1 ms scan)."""
    channel = Channel()
    text = "x" * 40_000
    replies: queue.Queue[CommandReply] = queue.Queue()
    sender = threading.Thread(target=lambda: replies.put(channel.send_command(
        CommandRequest(5, Command.DOWNLOAD, program_text=text), 30)))
    sender.start()
    drains, commands = 0, []
    for _ in range(100_000):
        if not channel._readable(channel._commands[0]):
            sender.join(timeout=0.001)
            continue
        drains += 1
        commands = channel.drain(budget_ns=0)[0]
        if commands:
            break
    assert [c.program_text for c in commands] == [text]
    frames = -(-len(text) // 3_900)  # at least: a frame carries under 4 KiB of it
    assert drains >= frames
    channel.reply(CommandReply(5, True, "ok", PlcState.STOPPED))
    sender.join(timeout=30)
    assert replies.get_nowait().ok


def test_a_held_reply_is_sent_by_send_held_or_the_next_drain() -> None:
    """reply(later=True) (the paced scan loop: answered after the scan's publish) sends
    nothing until send_held() or the next drain(); a reply for no drained command is
    refused when it is given, not when it is sent."""
    channel = Channel()
    replies: queue.Queue[CommandReply] = queue.Queue()
    senders = [threading.Thread(target=lambda n=n: replies.put(
        channel.send_command(CommandRequest(n, Command.STOP), 30))) for n in (8, 9)]
    drained: list[CommandRequest] = []
    for sender in senders:
        sender.start()
        for _ in range(10_000):
            if got := channel.drain()[0]:
                drained += got
                break
            sender.join(timeout=0.001)
    assert [r.id for r in drained] == [8, 9]
    with pytest.raises(ValueError, match="id 10"):
        channel.reply(CommandReply(10, True, "", PlcState.STOPPED), later=True)
    channel.reply(CommandReply(9, True, "second", PlcState.STOPPED), later=True)
    senders[1].join(timeout=0.3)
    assert senders[1].is_alive() and replies.empty()  # held: nothing sent yet
    channel.drain()  # the next scan's drain sends what was held
    senders[1].join(timeout=30)
    assert replies.get_nowait().message == "second"
    channel.reply(CommandReply(8, True, "first", PlcState.STOPPED), later=True)
    senders[0].join(timeout=0.3)
    assert senders[0].is_alive() and replies.empty()
    channel.send_held()
    senders[0].join(timeout=30)
    assert replies.get_nowait().message == "first"
    channel.close()
