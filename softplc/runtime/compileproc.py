"""The compile process: downloads compiled and analysed in a process of their own.

Owns: starting the compile process (spawned, in the background: SCHED_OTHER at nice 10, off
the scan's CPU when the scan is pinned), one
download at a time over a private pipe, a compile that dies or runs past COMPILE_TIMEOUT_S
turned into a refused download (the next download starts a new process), its budgets (a
download past COMPILE_MEMORY_BYTES of address space or COMPILE_CPU_S of CPU is refused, by
RLIMIT_AS and RLIMIT_CPU; after a MemoryError the process ends, the next download starts
another), and its end with the scan process (pipe closed, or PR_SET_PDEATHSIG); the same
process, at normal priority (`background=False`), for `softplc run`'s start and boot programs
(runtime/supervise/startprog.py: their requests know how they compile).
Why a process: threads of the scan process share one interpreter lock with the scan. Paced
between scans on a thread of the scan process (as it once was), a 10,000-transition compile
took ~3 s of the scan process's time and still cost slots at 1 ms; here it takes ~0.8 s of
another process's, and the scan thread only loads the result (program/wire.py), a step at a
time between scans (runtime/download.py). A
program that crashes or exhausts the compiler takes this process down, never the scan.
Does not know: the scan, the lifecycle, what compiling means (runtime/prepare.py).
"""

from __future__ import annotations

import contextlib
import gc
import math
import multiprocessing
import os
import pickle
import resource
import signal
import threading
import time
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

from softplc.core.problems import Problem, ProgramError
from softplc.core.snapshot import CommandRequest
from softplc.runtime import replyfile
from softplc.runtime.config import LoopConfig
from softplc.runtime.prepare import AnalysisRefused, Built, CompilerFailed, Preparer
from softplc.runtime.realtime import keep_off_scan_cpu

COMPILE_NICE = 10  # see idle()
COMPILE_TIMEOUT_S = 120.0  # one download's compile and analysis; then it is refused
# The compile process's budgets (docs/programs.md, size limits). Memory: address space
# above what the process maps once its imports are done (RLIMIT_AS; 159 MB measured): the
# 16,000-transition ring at the size limits peaked at 230 MB, the analysis gate's arrays
# are bounded to ~0.2 GB; a 70,000-place download once took it to 6,990 MiB and the
# machine into swap. CPU: seconds per download (RLIMIT_CPU, set again for each): that ring
# took 2.1 s, the gate's work budgets a few more.
COMPILE_MEMORY_BYTES = 1 << 30
COMPILE_CPU_S = 60
OUT_OF_MEMORY_EXIT = 86  # its exit code after a MemoryError (when the refusal could not go)
_CTX = multiprocessing.get_context("spawn")  # a fresh interpreter: nothing of the scan's


class Compilable(Protocol):
    """A request other than a download's, that knows how it compiles (runtime/supervise/
    startprog.py: `softplc run`'s start program and boot program); its answer is a value."""

    def compile(self, prep: Preparer) -> Any: ...


def compile_main(config: LoopConfig, conn: Connection,
                 memory_bytes: int = COMPILE_MEMORY_BYTES, cpu_s: float = COMPILE_CPU_S,
                 background: bool = True) -> None:
    """Entry point of the compile process: a request in, a Built (for a Compilable, what its
    compile returns) or an error out, until the scan process closes the pipe. A download over
    the memory or CPU budget is refused."""
    from softplc.runtime.shared.procs import die_with_parent, name_process

    name_process()  # softplc-compile (CompileProcess.start)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's business
    die_with_parent()
    prep = Preparer(config, lambda: None, lambda: ())
    if background:  # the CLI's start compile stays at normal priority: the start waits for it
        idle(0)  # imports done at normal priority (see starting()); every compile in background
    no_memory = replyfile.pack(("ended", CompilerFailed(_over_memory(memory_bytes))))
    _limit_memory(memory_bytes)
    signal.signal(signal.SIGXCPU, _out_of_cpu)
    while True:
        try:
            req = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            return  # the scan process is gone or closed the pipe
        _limit_cpu(cpu_s)
        gc.disable()  # collected once per download, below: full collections while the heap
        try:  # grows cost ~20 % of a big compile
            reply: tuple[str, Any] = ("ok", prep.build(req) if isinstance(req, CommandRequest)
                                      else req.compile(prep))
        except ProgramError as exc:  # paths as the sender knows them: a bundle's folder is here
            reply = ("error", ProgramError([
                Problem(prep.relative(p.file), p.line, p.path, prep.relative(p.message))
                for p in exc.problems]))
        except AnalysisRefused as exc:  # its findings are relative already
            reply = ("error", exc)
        except MemoryError:  # at its limit the heap stays full: the refusal, then the end
            _out_of_memory(conn, no_memory)
        except OutOfCpu:
            reply = ("error", CompilerFailed(
                f"the download needs more than the compile process's CPU budget of "
                f"{cpu_s:g} s; it is refused"))
        except Exception as exc:  # a compiler bug: the download is refused, the process lives
            reply = ("error", CompilerFailed(
                f"internal compiler error ({type(exc).__name__}: {exc})"))
        try:
            conn.send_bytes(replyfile.pack(reply))
        except (OSError, ValueError):
            return
        del reply
        _limit_cpu(None)
        gc.enable()
        gc.collect()  # between downloads, where nobody waits


def _over_memory(memory_bytes: int) -> str:
    return (f"the download needs more memory than the compile process's budget of "
            f"{memory_bytes >> 20:,} MiB; it is refused")


def _out_of_memory(conn: Connection, reply: bytes) -> None:
    """The refusal made before the budget was set, sent as it is; then the process ends (a
    new one takes the next download): once an allocation has failed at the limit, the heap
    is still mapped and the next one fails too (measured: every later step raised)."""
    with contextlib.suppress(BaseException):
        conn.send_bytes(reply)
    os._exit(OUT_OF_MEMORY_EXIT)


class OutOfCpu(BaseException):
    """SIGXCPU: the download spent the CPU budget (raised in the main thread; a
    BaseException, so that no `except Exception` in the compiler swallows it)."""


def _out_of_cpu(signum: int, frame: object) -> None:
    raise OutOfCpu


def _limit_memory(budget: int) -> None:
    """RLIMIT_AS at what is mapped now plus `budget`: past it an allocation fails with a
    MemoryError (a refusal), never a swap storm."""
    with open("/proc/self/statm", encoding="ascii") as statm:
        mapped = int(statm.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    soft = mapped + budget
    if hard != resource.RLIM_INFINITY:
        soft = min(soft, hard)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _limit_cpu(budget_s: float | None) -> None:
    """RLIMIT_CPU (soft) at the CPU time used so far plus `budget_s` (None: none). It counts
    the process's whole life, so it is set again for each download; the hard limit stays, so
    it can be raised again."""
    _, hard = resource.getrlimit(resource.RLIMIT_CPU)
    soft = resource.RLIM_INFINITY
    if budget_s is not None:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        soft = math.ceil(usage.ru_utime + usage.ru_stime + budget_s)
        if hard != resource.RLIM_INFINITY:
            soft = min(soft, hard)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_CPU, (soft, hard))


def idle(pid: int) -> None:
    """Background scheduling for `pid` (0: this process): SCHED_OTHER at nice COMPILE_NICE.
    Not SCHED_IDLE, which it was: beside CPU-bound work of any kind it got next to no CPU (a
    0.3 s compile took 50 s beside 3 busy loops on 2 cores, over 120 s beside 4, and every
    download ran out of its deadline). At nice 10 it takes about a tenth of a normal task's
    share when the CPUs are contended and all of them when they are not; a scan process
    waking at its deadline still preempts it (and with --scan-cpu it is kept off that CPU)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, pid, COMPILE_NICE)


def starting(pid: int) -> None:
    """A new compile process's scheduling while it imports (~0.35 s of CPU, once per
    process): SCHED_OTHER at the scan process's niceness, never the SCHED_FIFO it inherited.
    Not nice COMPILE_NICE yet: beside 4 busy loops on 2 cores, a tenth of a share stretched
    those imports to over 10 s, and the first download after every start waited for them
    (the API's clients gave up). It lowers itself once imported (compile_main)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0))


class CompileProcess:
    """The scan process's side: `build()` on the download helper thread (runtime/download.py,
    the one blocking exchange of a download); `start()` ahead of the first
    download (from the thread that stays: PR_SET_PDEATHSIG follows the thread that spawned
    it); `close()` on the way out."""

    def __init__(self, config: LoopConfig, timeout_s: float = COMPILE_TIMEOUT_S,
                 memory_bytes: int = COMPILE_MEMORY_BYTES, cpu_s: float = COMPILE_CPU_S,
                 background: bool = True) -> None:
        self.config = config
        self.timeout_s = timeout_s
        self.background = background
        self.budgets = (memory_bytes, cpu_s)  # the compile process's, per process/download
        self.started = 0  # processes started, for status and tests
        self.last_failure = ""  # why the last one ended while compiling (status)
        self.last_reply: dict[str, float] = {}  # its size, time to receive and to unpickle
        self._proc: Any = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()

    def start(self) -> None:
        with self._lock:
            if self._proc is not None and self._proc.is_alive():
                return
            self._end()
            mine, theirs = _CTX.Pipe(duplex=True)
            proc = _CTX.Process(target=compile_main,
                                args=(self.config, theirs, *self.budgets, self.background),
                                name="softplc-compile", daemon=True)
            proc.start()
            theirs.close()
            assert proc.pid is not None  # started
            starting(proc.pid)  # at once: it inherited the scan's policy (maybe SCHED_FIFO)
            keep_off_scan_cpu(proc.pid, self.config.realtime)
            self._proc, self._conn = proc, mine
            self.started += 1

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def info(self) -> dict[str, Any]:
        """For status: the process now, how many were started, the last failure."""
        return {"pid": self.pid, "started": self.started, "last_failure": self.last_failure,
                "last_reply": self.last_reply}

    def build(self, req: CommandRequest) -> Built:
        """Compile and analyse `req` in the compile process. Raises what the compile raised
        (ProgramError, AnalysisRefused) or CompilerFailed."""
        value = self.exchange(req)
        assert isinstance(value, Built)
        return value

    def exchange(self, req: CommandRequest | Compilable) -> Any:
        """One request, its answer (a Built, what a Compilable's compile returns) or what the
        compile raised."""
        self.start()
        conn, proc = self._conn, self._proc  # close() may clear them meanwhile
        assert conn is not None and proc is not None
        try:
            conn.send_bytes(pickle.dumps(req, protocol=5))
            # One wait for the answer or the process's end: no periodic wake-ups, each of
            # which would take the interpreter lock from the scan thread for a moment.
            if not wait([conn, proc.sentinel], self.timeout_s):
                self.close()
                self.last_failure = (f"the compile process took longer than "
                                     f"{self.timeout_s:g} s; it was stopped")
                raise CompilerFailed(self.last_failure)
            waited = time.monotonic_ns()
            reply = conn.recv_bytes()
            received = time.monotonic_ns()
            kind, value = replyfile.unpack(reply)
            self.last_reply = {"receive_ms": (received - waited) / 1e6,
                               "read_and_unpickle_ms": (time.monotonic_ns() - received) / 1e6}
            del reply
        except (EOFError, OSError, ValueError):
            raise CompilerFailed(self._died()) from None
        if kind == "ended":  # its last reply (out of memory): the next download gets a new one
            self.close()
            self.last_failure = str(value)
        if kind in ("error", "ended"):
            raise value
        return value

    def _died(self) -> str:
        """Why the compile process ended, said as a refusal; it is ended for good."""
        proc = self._proc
        if proc is not None:
            proc.join(1.0)
        code = proc.exitcode if proc is not None else None
        self.close()
        how = (f"killed by signal {-code}" if code is not None and code < 0
               else f"exit code {code}" if code is not None else "closed")
        if code is not None and -code in (signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT):
            # Some C code crashes where Python would raise a MemoryError (seen under RLIMIT_AS
            # budgets of a few MiB): the cause is likely, not known.
            how += f", perhaps at its memory budget of {self.budgets[0] >> 20:,} MiB"
        self.last_failure = (_over_memory(self.budgets[0]) if code == OUT_OF_MEMORY_EXIT else
                             f"the compile process ended while compiling ({how}); it restarts "
                             "with the next download")
        return self.last_failure

    def _end(self) -> None:
        """Close the pipe and end the process (the lock held)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        proc, self._proc = self._proc, None
        if proc is not None:
            proc.join(0.2)  # it leaves by itself once the pipe is closed
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)

    def close(self) -> None:
        """End the process (also from another thread while a build waits: it fails)."""
        with self._lock:
            self._end()
