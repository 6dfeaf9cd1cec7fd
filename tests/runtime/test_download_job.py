"""A download as one job (runtime/download.py): stepped between scans through its table of
stages, on the loop's own clock; commands after it keep their order, a stop or kill is never
held behind it; refusals typed; a download that cannot be kept as the boot program refused
before anything changes."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.snapshot import CommandReply, CommandRequest, Refusal
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.config import LoopConfig
from softplc.runtime.download import TABLE, Decided, Downloads, Stage, refusal_of
from softplc.runtime.loop import ScanLoop
from softplc.runtime.prepare import Built, Prepared, Preparer
from softplc.runtime.retain.writer import ContinuedClock
from softplc.runtime.shared.channel import Channel

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"
PACKAGE = ROOT / "softplc"


class GatedRemote:
    """The compile process's part, done by the real compiler on the helper thread once `gate`
    opens (a big program takes seconds)."""

    def __init__(self, config: LoopConfig, gate: threading.Event) -> None:
        self.inner = Preparer(config, lambda: None, lambda: ())
        self.gate = gate

    def build(self, req: CommandRequest) -> Built:
        assert self.gate.wait(20)
        return self.inner.build(req)


def gated_downloads(gate: threading.Event) -> Downloads:
    config = LoopConfig(root=str(ROOT))
    running = compile_file(TRANSPORT, ROOT)
    prep = Preparer(config, lambda: running, lambda: tuple(running.io.drivers.values()),
                    GatedRemote(config, gate))
    return Downloads(prep)


def step_until(downloads: Downloads, count: int, timeout_s: float = 20.0) -> list[Decided]:
    decided: list[Decided] = []
    deadline = time.monotonic() + timeout_s
    while len(decided) < count and time.monotonic() < deadline:
        downloads.work(time.monotonic_ns() + 2_000_000, time.monotonic_ns)
        decided += downloads.take()
        time.sleep(0.001)
    return decided


def test_the_job_table_reaches_an_end_from_every_stage() -> None:
    ends = {Stage.READY, Stage.ANSWERED, Stage.REFUSED}
    for stage in Stage:
        seen, todo = set(), [stage]
        while todo:
            now = todo.pop()
            seen.add(now)
            todo += [s for s in TABLE[now] if s not in seen]
        assert seen & ends, stage
        assert all(Stage.REFUSED in TABLE[s] for s in Stage if s not in ends)


def test_commands_behind_a_compiling_download_wait_and_keep_their_order() -> None:
    gate = threading.Event()
    downloads = gated_downloads(gate)
    text = TRANSPORT.read_text()
    downloads.put([CommandRequest(1, Command.RESET), CommandRequest(
        2, Command.DOWNLOAD, program_text=text, program_path=str(TRANSPORT)),
        CommandRequest(3, Command.START)])
    try:
        assert [d.request.id for d in downloads.take()] == [1]  # before the download: at once
        for _ in range(20):
            downloads.work(time.monotonic_ns() + 1_000_000, time.monotonic_ns)
            assert downloads.take() == []  # START waits for the download
        assert downloads.stage(2) is Stage.COMPILING and downloads.waiting == 2
        gate.set()
        rest = step_until(downloads, 2)
        assert [d.request.id for d in rest] == [2, 3]
        assert rest[0].prepared is not None and rest[0].error is None
        assert rest[0].prepared.net.name == compile_file(TRANSPORT).name
        assert rest[1].prepared is None and rest[1].error is None
    finally:
        gate.set()
        downloads.close()


@pytest.mark.parametrize("urgent", [Command.STOP, Command.KILL])
def test_a_stop_or_kill_is_never_held_behind_a_download(urgent: Command) -> None:
    gate = threading.Event()
    downloads = gated_downloads(gate)
    downloads.put([CommandRequest(1, Command.DOWNLOAD, program_text=TRANSPORT.read_text()),
                   CommandRequest(2, Command.RESET), CommandRequest(3, urgent)])
    try:
        first = downloads.take()  # nothing held, the order kept
        assert [d.request.id for d in first] == [1, 2, 3]
        kind, message, _ = refusal_of(first[0].error or RuntimeError(), str)
        assert kind is Refusal.WITHDRAWN
        assert f"a {urgent.value}, sent after it, was applied first" in message
    finally:
        gate.set()
        downloads.close()


def test_a_download_withdrawn_while_its_blocking_part_runs_leaves_nothing_behind(
        tmp_path: Path) -> None:
    """A stop withdraws a download whose boot program the helper thread is staging: what
    that work writes (or the devices it opens) is let go of when it ends, not leaked."""
    gate, written, staged = threading.Event(), threading.Event(), tmp_path / ".boot-staged"

    def keep(prepared: Prepared) -> None:  # the staging, held until the gate opens
        assert gate.wait(20)
        staged.write_text("boot program")
        prepared.staged = staged
        written.set()

    prep = Preparer(LoopConfig(root=str(ROOT)), lambda: None, lambda: ())
    prep.keep = keep
    downloads = Downloads(prep)
    downloads.put([CommandRequest(1, Command.DOWNLOAD, program_text=TRANSPORT.read_text(),
                                  program_path=str(TRANSPORT))])
    try:
        deadline = time.monotonic() + 20
        while downloads.stage(1) is not Stage.OPENING and time.monotonic() < deadline:
            downloads.work(None, time.monotonic_ns)
        assert downloads.stage(1) is Stage.OPENING
        downloads.put([CommandRequest(2, Command.STOP)])
        assert [d.request.id for d in downloads.take()] == [1, 2]
        gate.set()
        assert written.wait(20)
        deadline = time.monotonic() + 5  # the done-callback runs right after the work
        while staged.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not staged.exists()
    finally:
        gate.set()
        downloads.close()


def test_a_refused_download_carries_every_problem_typed() -> None:
    prep = Preparer(LoopConfig(root=str(ROOT)), lambda: None, lambda: ())
    downloads = Downloads(prep, threaded=False)
    downloads.put([CommandRequest(5, Command.DOWNLOAD, program_path="bad.yaml",
                                  program_text="program: x\nplaces: [\n")])
    downloads.work(None, time.monotonic_ns)
    (decided,) = downloads.take()
    kind, message, problems = refusal_of(decided.error or RuntimeError(), prep.relative)
    assert kind is Refusal.PROGRAM and kind.of_program
    assert message.startswith("download refused:\n")
    assert problems and all("bad.yaml:" in p for p in problems), problems


def send(channel: Channel, request: CommandRequest,
         replies: list[CommandReply]) -> threading.Thread:
    thread = threading.Thread(target=lambda: replies.append(channel.send_command(
        request, timeout_s=30)), daemon=True)
    thread.start()
    return thread


def run_loop(loop: ScanLoop) -> tuple[threading.Event, threading.Thread]:
    stop = threading.Event()
    thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
    thread.start()
    return stop, thread


def test_a_download_completes_on_a_clock_continued_from_a_snapshot(tmp_path: Path) -> None:
    """The warm-start hang (issue 26): a warm start continues the scan's clock from the
    snapshot, behind the host's monotonic clock by the downtime. Work between scans must run
    on the loop's clock: paced by the raw monotonic clock, its window was always in the past
    and the first download never finished, nor any command after it."""
    config = LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                        period_ns=10_000_000, state_dir=str(tmp_path / "state"))
    ScanLoop(replace(config, max_scans=20), None, None).run()  # its last snapshot at the end
    time.sleep(0.5)  # the downtime
    channel = Channel()
    loop = ScanLoop(config, channel, None)
    assert loop.start_mode == "warm" and isinstance(loop.clock, ContinuedClock)
    stop, thread = run_loop(loop)
    replies: list[CommandReply] = []
    try:
        send(channel, CommandRequest(1, Command.DOWNLOAD, program_text=TRANSPORT.read_text(),
                                     program_path=str(TRANSPORT), online=True,
                                     dry_run=True), replies).join(30)
        send(channel, CommandRequest(2, Command.STOP), replies).join(30)
        assert [r.id for r in replies] == [1, 2], replies
        assert replies[0].ok and "dry run" in replies[0].message, replies[0]
        assert replies[1].ok and replies[1].state is PlcState.STOPPED, (
            replies[1], loop.document().get("fault_reason"))
    finally:
        stop.set()
        thread.join(30)


@pytest.fixture
def state_fs(tmp_path: Path) -> Iterator[tuple[Path, Callable[[], None]]]:
    """A state directory and a way to make it refuse writes for real: a small tmpfs filled up
    as root (root writes through a mode), else the directory's mode made read-only."""
    mount = tmp_path / "fs"
    mount.mkdir()
    if os.geteuid() != 0:
        yield mount, lambda: mount.chmod(0o500)
        mount.chmod(0o700)
        return
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m,mode=0700", "tmpfs",
                           str(mount)], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount, lambda: fill(mount)
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(directory: Path) -> None:
    """Write until the file system has no byte free."""
    with (directory / "filler").open("wb") as out:
        try:
            while True:
                out.write(b"\0" * 65536)
                out.flush()
        except OSError:
            pass


def test_a_download_that_cannot_be_kept_as_boot_program_is_refused(
        state_fs: tuple[Path, Callable[[], None]]) -> None:
    """Answered ok and then lost at the next restart was the old way (issue 26): a state
    directory that cannot take the boot program refuses the download, the running program
    untouched."""
    state, refuse_writes = state_fs
    channel = Channel()
    loop = ScanLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                               state_dir=str(state), retain_interval_ns=0), channel, None,
                    VirtualClock(0))
    try:
        for _ in range(3):
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
        running = loop.runner.plc.net
        refuse_writes()
        replies: list[CommandReply] = []
        variant = TRANSPORT.read_text() + "\n# variant\n"
        sender = send(channel, CommandRequest(4, Command.DOWNLOAD, program_text=variant,
                                              program_path=str(TRANSPORT), online=True),
                      replies)
        deadline = time.monotonic() + 30
        while not replies and time.monotonic() < deadline:
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
            sender.join(0.001)
        (reply,) = replies
        assert not reply.ok and reply.refusal is Refusal.BOOT, reply
        assert "cannot be kept as the boot program" in reply.message
        assert loop.runner.plc.net is running and loop.runner.plc.state is PlcState.RUNNING
    finally:
        loop.shutdown()


def test_a_replaced_net_is_let_go_of_a_step_at_a_time_between_scans() -> None:
    """An online change: the old net's engine (and the net with it) is freed between scans,
    a container at a time, after the swap scan; freed at once, a 10,000-transition net's
    decref cascade took 7.4 ms."""
    import weakref

    channel = Channel()
    loop = ScanLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                               period_ns=10_000_000), channel, None)
    stop, thread = run_loop(loop)
    freed: list[str] = []
    try:
        deadline = time.monotonic() + 20
        while loop.runner.plc.engine is None and time.monotonic() < deadline:
            time.sleep(0.01)
        engine = loop.runner.plc.engine
        assert engine is not None
        watch = weakref.ref(engine, lambda _: freed.append(threading.current_thread().name))
        del engine
        replies: list[CommandReply] = []
        deadline = time.monotonic() + 30
        send(channel, CommandRequest(9, Command.DOWNLOAD, program_path=str(TRANSPORT),
                                     program_text=TRANSPORT.read_text() + "\n# variant\n",
                                     online=True), replies).join(30)
        assert replies and replies[0].ok, replies
        while watch() is not None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert watch() is None and freed == [thread.name], freed  # the scan thread's own
    finally:
        stop.set()
        thread.join(30)


def test_no_thread_pacing_is_left_in_the_package() -> None:
    """One owner steps a download between scans: no trace hook parks a compile thread, no
    switch interval is shortened for one (issue 27). The scan process sets its interval once,
    at its start, for every helper thread alike (runtime/realtime.py share_interpreter, issue
    40 item 8): the only place that may call it."""
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        for word in ("settrace", "setswitchinterval"):
            allowed = word == "setswitchinterval" and path == PACKAGE / "runtime" / "realtime.py"
            assert allowed or word not in text, f"{path.relative_to(ROOT)} uses {word}"
    realtime = (PACKAGE / "runtime" / "realtime.py").read_text()
    assert realtime.count("setswitchinterval") == 1  # once, in share_interpreter
    assert "getswitchinterval" not in realtime  # never put back: no toggling
