"""What `softplc run` compiles for a scan process, so that no scan process parses YAML
(docs/design.md section 12): its start program (compile_start, before), or else the state
directory's boot program (compile_boot: a start without a program, and every restart of the
scan process once a download was accepted; BootForms: unless the form it has serves it,
while that scan process starts).

Owns: the requests (StartRequest, BootRequest) and their compiled form (StartProgram, what the
scan process loads: runtime/bootkeeper.py); where they compile: a program up to IN_CLI_BYTES
in `softplc run` itself (starting a process costs ~0.5 s of CPU, a small compile ~10 ms), a
bigger one in a compile process of its own at normal priority (runtime/compileproc.py, its
budgets); a boot program that no longer compiles as a StartProgram with its `problem`,
which the scan process reports (never a failed start).
Does not know: the scan, the supervisor's restarts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import threading
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.program import boot, wire
from softplc.program import bundle as bundles
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime.bootkeeper import Awaited
from softplc.runtime.compileproc import COMPILE_TIMEOUT_S, CompileProcess
from softplc.runtime.config import LoopConfig
from softplc.runtime.prepare import CompilerFailed, Preparer

IN_CLI_BYTES = 64 << 10  # a program up to this is compiled in `softplc run` itself
HERE, COMPILE_PROCESS = "softplc run", "softplc run's compile process"  # compiled_in


@dataclass(frozen=True, slots=True)
class StartProgram:
    """A program compiled for a start: the net as bytes (program/wire.py), as a download's, and
    its analysis (reported, never a refusal: the person at the console chose it, or the PLC
    accepted it). The supervisor hands it to every scan process it starts
    (LoopConfig.compiled), so neither a start nor a restart parses YAML. `conflict`: why it
    cannot run with --plant ("" if it can); `problem`: why the boot program no longer
    compiles ("" if it does)."""

    net: tuple[bytes, ...]
    analysis: dict[str, Any] | None
    program_hash: str
    compiled_by: int  # the pid of the process that compiled it
    conflict: str = ""
    boot: Any = None  # its boot program (program/boot.py BootProgram: the bundle read here)
    compiled_in: str = HERE  # which process that pid was, for status
    problem: str = ""

    def load(self) -> CompiledNet:
        """The net, loaded from its bytes (expressions compiled again, program/wire.py)."""
        return wire.loads(self.net)

    def serves(self, program: boot.BootProgram) -> bool:
        """Is this the compiled form of `program` (a boot program read from the state dir)?"""
        return self.boot == program or (
            bool(self.program_hash) and self.program_hash == program.program_hash)


@dataclass(frozen=True, slots=True)
class StartRequest:
    """`softplc run`'s program, to compile once; `plant` a --plant it must not conflict with."""

    path: str
    plant: str | None = None
    compiled_in: str = HERE

    def compile(self, prep: Preparer) -> StartProgram:
        """In the process that compiles it (`softplc run`, or the compile process)."""
        from softplc.runtime.runner import plant_conflict

        net = compile_file(self.path)
        conflict = (plant_conflict(net.io, self.plant) or "") if self.plant else ""
        if conflict:
            return StartProgram((), None, net.program_hash, os.getpid(), conflict,
                                compiled_in=self.compiled_in)
        return StartProgram(wire.dumps(net), prep.analyse(net, gate=False), net.program_hash,
                            os.getpid(), boot=boot.from_file(self.path, net.program_hash),
                            compiled_in=self.compiled_in)


@dataclass(frozen=True, slots=True)
class BootRequest:
    """The state directory's boot program, to compile for a scan process about to start."""

    program: boot.BootProgram
    compiled_in: str = HERE

    def compile(self, prep: Preparer) -> StartProgram:
        """As the scan process compiled it before: a bundle unpacked anew (in the state dir),
        a text against its root; what fails to compile is the `problem`."""
        program = self.program
        try:
            net = (prep.compile_bundle(program.bundle) if program.bundle is not None else
                   compile_text(program.text, program.filename,
                                Path(program.root) if program.root else None))
        except (ProgramError, bundles.BundleError, OSError) as exc:
            return StartProgram((), None, "", os.getpid(), boot=program,
                                compiled_in=self.compiled_in, problem=str(exc))
        return StartProgram(wire.dumps(net), prep.analyse(net, gate=False), net.program_hash,
                            os.getpid(), boot=program, compiled_in=self.compiled_in)


def compile_start(req: StartRequest, verify: str = "warn",
                  timeout_s: float = COMPILE_TIMEOUT_S) -> StartProgram:
    """`softplc run`'s program compiled and analysed once (where: _compiled). Raises
    ProgramError or CompilerFailed."""
    with contextlib.suppress(OSError):  # unreadable: the compile says so, with its location
        if os.path.getsize(req.path) <= IN_CLI_BYTES:
            return _compiled(req, LoopConfig(verify=verify), timeout_s, here=True)
    return _compiled(req, LoopConfig(verify=verify), timeout_s, here=False)


def compile_boot(program: boot.BootProgram, config: LoopConfig,
                 timeout_s: float = COMPILE_TIMEOUT_S) -> StartProgram:
    """The boot program compiled and analysed for a scan process about to start, with the
    configuration it runs under (its root, state dir: a bundle unpacked where that process
    would). Never raises: a compile that fails or dies is the StartProgram's `problem`."""
    try:
        return _compiled(BootRequest(program), config, timeout_s,
                         here=_size(program) <= IN_CLI_BYTES)
    except (ProgramError, CompilerFailed) as exc:
        return StartProgram((), None, "", os.getpid(), boot=program, problem=str(exc))
    except Exception as exc:  # a compiler bug must not take the supervisor down
        return StartProgram((), None, "", os.getpid(), boot=program,
                            problem=f"internal compiler error ({type(exc).__name__}: {exc})")


class BootForms:
    """The supervisor's boot program, compiled for the scan processes it starts: a scan process
    starts at once (its imports, ~0.5 s of CPU, while the boot program compiles on a thread of
    the supervisor) and waits for the form (bootkeeper.Awaited), which is kept for the next
    restart; one compile per boot program, whatever restarts come meanwhile."""

    def __init__(self, ctx: Any) -> None:
        self.ctx = ctx  # the supervisor's multiprocessing context (spawn): its pipes
        self._job: _BootJob | None = None

    def for_scan(self, config: LoopConfig) -> tuple[LoopConfig, Any]:
        """The supervisor's configuration (holding the last form compiled) and what a scan
        process about to start without a program gets as LoopConfig.compiled: a form that
        serves the state directory's boot program, else an Awaited one; `config.compiled`
        when there is none or it cannot be read (the scan process says why)."""
        job = self._job
        if job is not None and job.result is not None:
            config, self._job = dataclasses.replace(config, compiled=job.result), None
        if not config.state_dir or not config.boot:
            return config, config.compiled
        try:
            program = boot.load(config.state_dir)
        except boot.BootUnreadable:
            return config, config.compiled
        if program is None or (config.compiled is not None and config.compiled.serves(program)):
            return config, config.compiled
        if self._job is None or self._job.program != program:
            self._job = _BootJob(program, config)
        return config, self._job.awaited(self.ctx)

    @staticmethod
    def started(given: Any) -> None:
        """After the scan process was spawned with `given`: this process's end of its pipe
        closed, so that a scan process gone before it read makes the send fail, not block."""
        if isinstance(given, Awaited):
            given.close()

    def cancel(self) -> None:
        """At a stop: a scan process still waiting gets no form (it starts with no program)."""
        if self._job is not None:
            self._job.cancel()


class _BootJob:
    """One compile of a boot program (compile_boot) on a thread, its form sent to every scan
    process that waits for it."""

    def __init__(self, program: boot.BootProgram, config: LoopConfig) -> None:
        self.program, self.config = program, config
        self.result: StartProgram | None = None
        self._lock = threading.Lock()
        self._waiting: list[Connection] = []
        threading.Thread(target=self._run, name="boot-compile", daemon=True).start()

    def awaited(self, ctx: Any) -> StartProgram | Awaited:
        with self._lock:
            if self.result is not None:
                return self.result
            theirs, mine = ctx.Pipe(duplex=False)
            self._waiting.append(mine)
        return Awaited(theirs)

    def _run(self) -> None:
        result = compile_boot(self.program, self.config)
        data = pickle.dumps(result, protocol=5)
        with self._lock:
            self.result, waiting, self._waiting = result, self._waiting, []
        for conn in waiting:  # a scan process reads it after its imports
            with contextlib.suppress(OSError, ValueError):  # gone meanwhile
                conn.send_bytes(data)
            conn.close()

    def cancel(self) -> None:
        with self._lock:
            waiting, self._waiting = self._waiting, []
        for conn in waiting:
            conn.close()


def _size(program: boot.BootProgram) -> int:
    """What a compile of it reads: its text, or every file of its bundle."""
    if program.bundle is None:
        return len(program.text.encode())
    try:
        return sum(len(data) for data in bundles.unpack(program.bundle).files.values())
    except bundles.BundleError:
        return 0  # refused at once, wherever it compiles


def _compiled(req: StartRequest | BootRequest, config: LoopConfig, timeout_s: float,
              here: bool) -> StartProgram:
    """In `softplc run` itself, or in a compile process of its own at normal priority (the
    start waits for it; ended after)."""
    if here:
        return req.compile(Preparer(config, lambda: None, lambda: ()))
    compiler = CompileProcess(config, timeout_s, background=False)
    try:
        value = compiler.exchange(dataclasses.replace(req, compiled_in=COMPILE_PROCESS))
    finally:
        compiler.close()
    assert isinstance(value, StartProgram)
    return value
