"""The boot program at work: which program a starting PLC runs, and every accepted download
kept as the next start's program (written off the scan).

Owns: the command line's program or else the state directory's boot program, loaded as
`softplc run` compiled it (config.compiled; Awaited: still compiling while this process
started); the boot program rewritten only when it changed; a download staged as the next
boot program before it is decided (a disk that cannot take it refuses the download:
BootNotKept) and put in force when it is accepted. Storage itself: program/boot.py.
Does not know: the scan, the channel.
"""

from __future__ import annotations

import contextlib
import pickle
import time
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.program import boot
from softplc.program import bundle as bundles
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime.config import LoopConfig
from softplc.runtime.prepare import DownloadRefused, Prepared, Preparer
from softplc.runtime.runner import plant_conflict


class BootNotKept(DownloadRefused):
    """A download refused because it could not be kept as the boot program."""


class Awaited:
    """A start program that `softplc run` is compiling while this process starts
    (supervise/startprog.py BootForms): it comes over a pipe from the supervisor (a StartProgram;
    None when the supervisor stopped first)."""

    def __init__(self, conn: Connection | None) -> None:
        self._conn = conn

    def __reduce__(self) -> tuple[type[Awaited], tuple[Connection | None]]:
        # Spawned with it: its pipe; once read (the config goes on to the compile process): none
        conn = self._conn
        return Awaited, (None if conn is None or conn.closed else conn,)

    def receive(self) -> Any:
        if self._conn is None:
            return None
        try:
            value = pickle.loads(self._conn.recv_bytes())  # from the supervisor, our parent
        except (EOFError, OSError):
            value = None
        self._conn.close()
        return value

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()


class BootKeeper:
    """`source` says where the running program came from; `problem` why the boot program
    could not be kept, if it could not."""

    def __init__(self, config: LoopConfig, prep: Preparer) -> None:
        self.config = config
        self._prep = prep
        self.source = config.program or "none"
        self.problem = ""
        self.started: dict[str, Any] = {}  # how the start program came (start())
        self._writer: ThreadPoolExecutor | None = None
        self._later: list[tuple[Path, boot.BootProgram]] = []
        if config.state_dir is not None:
            prep.keep = self.stage

    def start(self, prep: Preparer) -> tuple[CompiledNet | None, dict[str, Any] | None]:
        """The program a start runs, and its analysis (reported, never a refusal: the person
        at the console chose it, or the PLC accepted it): loaded from what `softplc run`
        compiled (config.compiled: the command line's program or the boot program) when it is
        that program, else compiled and analysed here (a loop built directly). `started` says
        which, for status."""
        began, compiled = time.monotonic_ns(), self.config.compiled
        if isinstance(compiled, Awaited):
            compiled = compiled.receive()
            if compiled is None:
                self.source = "none (softplc run stopped before the boot program compiled)"
                return None, None
        net, _ = self.program(compiled)
        if net is None:
            return None, None
        loaded = compiled is not None and net.program_hash == compiled.program_hash
        analysis = compiled.analysis if loaded else prep.analyse(net, gate=False)
        self.started = {"compiled_by": f"{compiled.compiled_in} (pid {compiled.compiled_by})"
                        if loaded else "scan process",
                        "ready_ms": round((time.monotonic_ns() - began) / 1e6, 1)}
        return net, analysis

    def program(self, compiled: Any = None) -> tuple[CompiledNet | None, boot.BootProgram | None]:
        """The program to run: the command line's, else the boot program of the state dir.
        `softplc run` compiles either before this process starts and reports its errors:
        `compiled` (a StartProgram, runtime/supervise/startprog.py) is loaded, not compiled
        again, for the program it serves; only a loop built without it compiles here."""
        config = self.config
        if config.program:
            if compiled is not None:
                net = compiled.load()
            elif config.plant and (why := plant_conflict(compile_file(config.program).io,
                                                         config.plant)):
                raise ValueError(why)
            else:
                net = compile_file(config.program)
            program = (compiled.boot if compiled is not None  # its bundle: read by the compiler
                       else boot.from_file(config.program, net.program_hash))
            if config.state_dir is not None:  # the program the PLC runs is its boot program
                self._save(program, unless_same=True)
            return net, program
        if config.state_dir is None or not config.boot:
            return None, None
        try:
            loaded = boot.load(config.state_dir)
        except boot.BootUnreadable as exc:
            self.source = f"none ({exc})"
            return None, None
        if loaded is None:
            return None, None
        program = loaded
        if compiled is not None and compiled.serves(program) and compiled.problem:
            return self._no_longer(program, compiled.problem)  # as `softplc run` found
        try:
            if compiled is not None and compiled.serves(program):
                net = compiled.load()
            elif program.bundle is not None:
                net = self._prep.compile_bundle(program.bundle)  # unpacked anew if removed
            else:
                net = compile_text(program.text, program.filename,
                                   Path(program.root) if program.root else None)
        except (ProgramError, bundles.BundleError, OSError) as exc:
            return self._no_longer(program, str(exc))
        self.source = program.describe()
        return net, program

    def _no_longer(self, program: boot.BootProgram, why: str) -> tuple[None, None]:
        self.source = f"none ({program.describe()} no longer compiles: {why})"
        return None, None

    def stage(self, prepared: Prepared) -> None:
        """On the download's helper thread, before the download is decided: the program
        written beside the boot program, so that a download the PLC could not keep across a
        restart is refused (BootNotKept) rather than answered ok and lost at the next start."""
        program = self._prep.boot_program(prepared.request, prepared.net)
        encoded, prepared.boot_file = prepared.boot_file, None
        if program is None or self.config.state_dir is None:
            return
        try:
            prepared.staged = boot.stage(self.config.state_dir, program, encoded)
            prepared.boot_program = program
        except OSError as exc:
            raise BootNotKept(
                f"it cannot be kept as the boot program in {self.config.state_dir} "
                f"({exc.strerror or exc}): a restart would run the older program; nothing "
                "was changed") from None

    def keep(self, prepared: Prepared, later: bool = False) -> None:
        """The accepted download becomes the boot program: its staged file put in force (one
        rename, off the scan). `later`: handed to the writer thread at settle(), after the
        scan (woken in the scan, the thread took the interpreter from it for 0.1-0.4 ms
        of the swap scan at a switch interval of 0.2 ms); `source` says it at once."""
        staged, prepared.staged = prepared.staged, None
        program, prepared.boot_program = prepared.boot_program, None  # described when staged
        if program is None or staged is None:
            return
        self._later.append((staged, program))
        self.source = program.describe()
        if not later:
            self.settle()

    def settle(self) -> None:
        """What keep() left for later, to the writer thread."""
        while self._later:
            if self._writer is None:
                self._writer = ThreadPoolExecutor(1, thread_name_prefix="boot")
            self._writer.submit(self._commit, *self._later.pop(0))

    def _commit(self, staged: Path, program: boot.BootProgram) -> None:
        try:
            boot.commit(staged)
            self.problem = ""
        except OSError as exc:  # the staged file was written: only a rename failed
            self.problem = (f"{program.describe()} not saved in {self.config.state_dir}: "
                            f"{exc.strerror or exc}")

    def _save(self, program: boot.BootProgram, unless_same: bool = False) -> None:
        """Keep `program` as the boot program. A full or read-only disk never stops the PLC:
        the failure is shown in status (`boot_problem`) and the previous boot program stays."""
        assert self.config.state_dir is not None
        try:
            if unless_same:
                with contextlib.suppress(boot.BootUnreadable):
                    kept = boot.load(self.config.state_dir)
                    if kept is not None and kept.program_hash == program.program_hash:
                        return  # a restart of the same program: nothing to write
            boot.save(self.config.state_dir, program)
            self.problem = ""
        except OSError as exc:
            self.problem = (f"{program.describe()} not saved in {self.config.state_dir}: "
                                 f"{exc.strerror or exc}")

    def close(self) -> None:
        """Wait for a boot program being written (one kept for later written first)."""
        self.settle()
        if self._writer is not None:
            self._writer.shutdown(wait=True)
