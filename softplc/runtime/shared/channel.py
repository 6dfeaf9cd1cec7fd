"""Commands and HMI writes to the scan process, and command replies back to their callers.

Owns: Channel (scan side: drain, reply; client side: send_command, send_hmi_write), the
framing of messages into pipe-atomic frames, reply lanes. Its exceptions (ChannelFull,
NotQueued, NoReply) are in core/snapshot.py, where its callers import them too.
Does not know: what a command does, the scan loop, Modbus, HTTP.

Create the Channel before starting processes and pass it to them (spawn or fork; create it
with the context that starts them). Three kinds of OS pipe from multiprocessing.Pipe:

- commands and HMI writes, clients -> scan: every message is cut into frames of at most
  PIPE_BUF bytes, which POSIX writes atomically, so several writers need no lock, and the
  scan never finds half a message: drain() polls and reads, and can never block, even if a
  client is killed mid-send. Write ends are non-blocking: a full pipe refuses the frame
  instead of stalling the writer. The kernel buffer (64 KiB on Linux, about 570
  single-register writes) is the queue bound; commands have their own pipe, so a flood of
  HMI writes cannot hold back a stop or kill.
- replies, scan -> clients: one pipe ("lane") per client process, claimed on its first
  command by pid and reclaimed from dead processes. A dispatcher thread in the client routes
  each reply to the waiting thread by ticket, so any number of threads may have commands in
  flight. Replies that do not fit in the pipe wait in the scan process and go out at the
  next drain() or reply(); the scan side never blocks.

POSIX only (PIPE_BUF atomicity, non-blocking pipes), like the shared-memory snapshot.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import pickle
import secrets
import select
import threading
import time
from array import array
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.context import BaseContext
from typing import Any, Final

from softplc.core.image import Address
from softplc.core.snapshot import (
    ChannelFull,
    CommandReply,
    CommandRequest,
    HmiWrite,
    NoReply,
    NotQueued,
)
from softplc.runtime.clock import MonotonicClock

FRAME_BYTES: Final = select.PIPE_BUF - 4  # Connection.send_bytes adds a 4-byte length
_CHUNK_BYTES: Final = FRAME_BYTES - 128  # room for the pickled (ticket, lane, i, n) tuple
_MAX_PARTIAL: Final = 64  # half-received commands kept (their clients died or gave up)
_MAX_BACKLOG: Final = 1024  # reply frames kept for a lane whose reader is not reading
_MAX_ABANDONED: Final = 1024  # commands whose caller gave up, kept for a late reply
_CLOCK: Final = MonotonicClock()


@dataclass(slots=True)
class _Pending:
    done: threading.Event = field(default_factory=threading.Event)
    chunks: list[bytes] = field(default_factory=list)
    reply: CommandReply | None = None
    late: Callable[[CommandReply], None] | None = None  # its caller gave up but wants to know


@dataclass(slots=True)
class _Client:
    """Client state of one process: its reply lane, tickets, and callers awaiting replies."""

    pid: int
    lane: int
    tickets: Iterator[int]
    pending: dict[int, _Pending] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


_CLIENT_LOCK = threading.Lock()
if hasattr(os, "register_at_fork"):
    # A lock held by another thread at fork time would stay held forever in the child.
    def _new_client_lock() -> None:
        global _CLIENT_LOCK
        _CLIENT_LOCK = threading.Lock()

    os.register_at_fork(after_in_child=_new_client_lock)


class Channel:
    """The scan process calls drain() and reply() (from one thread); clients call
    send_command() and send_hmi_write() from any thread of any process that received the
    Channel. At most `lanes` live processes can send commands; HMI writes are unlimited."""

    def __init__(
        self, *, lanes: int = 4, drain_limit: int = 64, ctx: BaseContext | None = None
    ) -> None:
        if lanes <= 0 or drain_limit <= 0:
            raise ValueError("a channel needs at least one reply lane and a drain limit >= 1")
        context = ctx or mp.get_context()
        self.drain_limit = drain_limit
        self._commands: tuple[Connection, Connection] = context.Pipe(duplex=False)
        self._hmi: tuple[Connection, Connection] = context.Pipe(duplex=False)
        self._lanes: list[tuple[Connection, Connection]] = [
            context.Pipe(duplex=False) for _ in range(lanes)
        ]
        self._owners = context.Array("q", lanes)  # pid holding each lane; 0 = free
        for _, writer in (self._commands, self._hmi, *self._lanes):
            os.set_blocking(writer.fileno(), False)  # shared by every process holding it
        self._init_local()

    def close(self) -> None:
        """Close this process's ends of every pipe (the owner, when nobody sends any more):
        a channel holds 2 + lanes pipes, and one left to the garbage collector keeps them
        open for as long as anything refers to it."""
        for reader, writer in (self._commands, self._hmi, *self._lanes):
            reader.close()
            writer.close()
        self._ready.clear()

    def _init_local(self) -> None:
        self._client: _Client | None = None
        # Received frames of each command being assembled: one buffer grown frame by frame,
        # so that its pages are touched a frame per drain rather than all at the last frame.
        self._partial: dict[tuple[int, int], tuple[int, bytearray]] = {}
        self._awaiting: dict[int, deque[tuple[int, int]]] = {}
        self._backlog: dict[int, deque[bytes]] = {}
        self._ready: dict[int, select.poll] = {}  # Connection.poll() costs ~5 µs a call
        self._held: deque[CommandReply] = deque()  # reply(later=True)

    def _readable(self, reader: Connection) -> bool:
        fd = reader.fileno()
        poller = self._ready.get(fd)
        if poller is None:
            poller = self._ready[fd] = select.poll()
            poller.register(fd, select.POLLIN)
        return bool(poller.poll(0))

    def __getstate__(self) -> dict[str, Any]:
        keep = ("drain_limit", "_commands", "_hmi", "_lanes", "_owners")
        return {name: getattr(self, name) for name in keep}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for name, value in state.items():
            setattr(self, name, value)
        self._init_local()

    # -- scan side -------------------------------------------------------------------------

    def drain(self, budget_ns: int | None = None) -> tuple[list[CommandRequest], list[HmiWrite]]:
        """Everything that arrived, in arrival order, without blocking. At most `drain_limit`
        frames of each kind per call, and command frames only while `budget_ns` lasts (at
        least one: a 500 KB download is ~125 frames of 4 KiB, the 16 a full pipe holds took
        1.3 ms of a 1 ms scan); the rest waits for the next call. Every drained command must
        get exactly one reply(), in drain order among commands that share an id."""
        self.send_held()
        self._flush_replies()
        commands: list[CommandRequest] = []
        reader = self._commands[0]
        until = None if budget_ns is None else time.perf_counter_ns() + budget_ns
        for n in range(self.drain_limit):
            if (n and until is not None and time.perf_counter_ns() > until) \
                    or not self._readable(reader):
                break
            ticket, lane, index, count, chunk = pickle.loads(reader.recv_bytes())
            request = self._assemble((lane, ticket), index, count, chunk)
            if request is not None:
                self._awaiting.setdefault(request.id, deque()).append((lane, ticket))
                commands.append(request)
        writes: list[HmiWrite] = []
        reader = self._hmi[0]
        for _ in range(self.drain_limit):
            if not self._readable(reader):
                break
            writes.append(_decode_hmi(reader.recv_bytes()))
        return commands, writes

    def _assemble(
        self, key: tuple[int, int], index: int, count: int, chunk: bytes
    ) -> CommandRequest | None:
        received, blob = self._partial.get(key, (0, bytearray()))
        if index != received:  # a frame lost to a timed-out sender: drop the command
            self._partial.pop(key, None)
            return None
        blob += chunk
        if index + 1 < count:
            self._partial[key] = (index + 1, blob)
            if len(self._partial) > _MAX_PARTIAL:
                del self._partial[next(iter(self._partial))]
            return None
        self._partial.pop(key, None)
        request: CommandRequest = pickle.loads(blob)
        return request

    def reply(self, reply: CommandReply, later: bool = False) -> None:
        """Send `reply` to the caller of the drained command with the same id. Never blocks.
        `later`: held (not yet encoded) until send_held() or the next drain()."""
        waiting = self._awaiting.get(reply.id)
        if not waiting:
            raise ValueError(f"no drained command with id {reply.id} is waiting for a reply")
        if later:
            self._held.append(reply)
            return
        lane, ticket = waiting.popleft()
        if not waiting:
            del self._awaiting[reply.id]
        backlog = self._backlog.setdefault(lane, deque(maxlen=_MAX_BACKLOG))
        backlog.extend(_frames(pickle.dumps(reply, pickle.HIGHEST_PROTOCOL), (ticket,)))
        self._flush_replies()

    def send_held(self) -> None:
        """The replies held by reply(later=True), in the order they were given."""
        while self._held:
            self.reply(self._held.popleft())

    def _flush_replies(self) -> None:
        for lane, backlog in self._backlog.items():
            writer = self._lanes[lane][1]
            while backlog:
                try:
                    writer.send_bytes(backlog[0])
                except BlockingIOError:
                    break  # the client is not reading; retried at the next drain()
                except BrokenPipeError:
                    backlog.clear()
                    break
                backlog.popleft()

    # -- client side -----------------------------------------------------------------------

    def send_command(self, request: CommandRequest, timeout_s: float = 5.0,
                     on_late: Callable[[CommandReply], None] | None = None) -> CommandReply:
        """Queue `request` for the scan process and wait for its reply. Raises NotQueued if it
        cannot be queued within `timeout_s`, NoReply if it is not answered in time (both are
        TimeoutErrors: the scan process is not running or not draining). With `on_late`, a
        reply that comes after NoReply is handed to it (from the reply thread)."""
        deadline_ns = _CLOCK.now_ns() + int(timeout_s * 1e9)
        client = self._client_state()
        ticket = next(client.tickets)
        pending = _Pending()
        with client.lock:
            client.pending[ticket] = pending
        try:
            blob = pickle.dumps(request, pickle.HIGHEST_PROTOCOL)
            for frame in _frames(blob, (ticket, client.lane)):
                if not self._send_until(frame, deadline_ns):
                    raise NotQueued(
                        f"command {request.command.value} (id {request.id}) could not be queued "
                        f"within {timeout_s} s: the scan process is not draining its commands"
                    )
            if not pending.done.wait(max(0.0, (deadline_ns - _CLOCK.now_ns()) / 1e9)):
                if on_late is not None:
                    pending.late = on_late
                raise NoReply(
                    f"no reply to command {request.command.value} (id {request.id}) within "
                    f"{timeout_s} s: is the scan process running?"
                )
            assert pending.reply is not None
            return pending.reply
        finally:
            with client.lock:
                if pending.late is None or pending.done.is_set():
                    del client.pending[ticket]
                elif len(client.pending) > _MAX_ABANDONED:  # nobody answers: forget the oldest
                    del client.pending[next(iter(client.pending))]

    def _send_until(self, frame: bytes, deadline_ns: int) -> bool:
        writer = self._commands[1]
        while True:
            try:
                writer.send_bytes(frame)
                return True
            except BlockingIOError:
                remaining_s = (deadline_ns - _CLOCK.now_ns()) / 1e9
                if remaining_s <= 0:
                    return False
                select.select([], [writer], [], remaining_s)

    def send_hmi_write(self, write: HmiWrite) -> None:
        """Queue `write` for the next scan start, never blocking: a full queue raises
        ChannelFull and the write is not applied."""
        try:
            self._hmi[1].send_bytes(_encode_hmi(write))
        except BlockingIOError:
            raise ChannelFull(
                f"HMI write to {write.address} refused: the scan process has not drained the "
                "previous writes (queue full)"
            ) from None

    def _client_state(self) -> _Client:
        client = self._client
        if client is not None and client.pid == os.getpid():
            return client
        with _CLIENT_LOCK:
            client = self._client
            if client is None or client.pid != os.getpid():
                lane = self._claim_lane()
                start = secrets.randbits(62)  # tickets of a lane's previous owner never match
                client = _Client(os.getpid(), lane, itertools.count(start))
                thread = threading.Thread(
                    target=self._dispatch, args=(client,), name="softplc-replies", daemon=True
                )
                thread.start()
                self._client = client
            return client

    def _claim_lane(self) -> int:
        pid = os.getpid()
        with self._owners.get_lock():
            for lane in range(len(self._lanes)):
                owner: int = self._owners[lane]
                if owner == 0 or (owner != pid and not pid_alive(owner)):
                    self._owners[lane] = pid
                    return lane
        raise ChannelFull(
            f"all {len(self._lanes)} reply lanes are held by live processes: create the "
            "Channel with more lanes for more processes sending commands"
        )

    def _dispatch(self, client: _Client) -> None:
        """Route reply frames from this process's lane to the threads waiting for them."""
        reader = self._lanes[client.lane][0]
        while True:
            try:
                ticket, index, count, chunk = pickle.loads(reader.recv_bytes())
            except (EOFError, OSError):
                return
            late = None
            with client.lock:
                pending = client.pending.get(ticket)
                if pending is None or index != len(pending.chunks):
                    continue  # its caller gave up, or it belongs to the lane's previous owner
                pending.chunks.append(chunk)
                if len(pending.chunks) == count:
                    pending.reply = pickle.loads(b"".join(pending.chunks))
                    pending.done.set()
                    if pending.late is not None:
                        late = pending.late
                        del client.pending[ticket]
            if late is not None and pending.reply is not None:
                late(pending.reply)


def _frames(blob: bytes, prefix: tuple[int, ...]) -> list[bytes]:
    """`blob` cut into pickled (*prefix, index, count, chunk) frames of at most FRAME_BYTES."""
    chunks = [blob[i : i + _CHUNK_BYTES] for i in range(0, len(blob), _CHUNK_BYTES)] or [b""]
    return [
        pickle.dumps((*prefix, i, len(chunks), chunk), pickle.HIGHEST_PROTOCOL)
        for i, chunk in enumerate(chunks)
    ]


def _encode_hmi(write: HmiWrite) -> bytes:
    """One frame: the values packed as bytes (coils) or uint16 (registers)."""
    values = write.values
    if not all(0 <= v <= 0xFFFF for v in values):
        raise ValueError(f"HMI write to {write.address}: values must be in 0..65535")
    code = "B" if all(v <= 0xFF for v in values) else "H"
    frame = pickle.dumps(
        (write.address, code, array(code, values).tobytes()), pickle.HIGHEST_PROTOCOL
    )
    if len(frame) > FRAME_BYTES:
        raise ValueError(
            f"HMI write to {write.address} of {len(values)} values is too long for one frame"
        )
    return frame


def _decode_hmi(frame: bytes) -> HmiWrite:
    address, code, raw = pickle.loads(frame)
    assert isinstance(address, Address)
    values = array(code)
    values.frombytes(raw)
    return HmiWrite(address, tuple(values))


def pid_alive(pid: int) -> bool:
    if os.name != "posix":
        return True  # no cheap probe: never reclaim
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
