"""The Modbus process's scheduler slice (runtime/serve/timeslice.py, comm.MODBUS_SLICE_NS;
docs/design.md section 7). A real `softplc run`: its Modbus process runs with the short slice
on every thread, the HTTP process with the kernel's base slice. Another where the kernel
refuses the call (a seccomp filter answering EPERM to sched_setattr, installed before exec
and inherited by every process of the PLC): Modbus serves as before, and the refusal is one
log line. Loopback ports, the processes ended at the end whatever happened.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import json
import platform
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from softplc.runtime.serve.comm import MODBUS_SLICE_NS, CommConfig, service_groups
from softplc.runtime.serve.timeslice import SliceAnswer, request_slice, slice_of
from tests.runtime.test_service_groups import listener, scan_count
from tests.support import eventually, free_port, stop_process

ROOT = Path(__file__).resolve().parents[2]
wait_for = functools.partial(eventually, timeout_s=60.0, step_s=0.1)
SCHED_SETATTR_X86_64 = 314


def _kernel_takes_slices() -> bool:
    """Asked in a child process: the test process keeps its own slice."""
    probe = ("from softplc.runtime.serve.timeslice import request_slice\n"
             "raise SystemExit(0 if request_slice(100_000).ok else 1)")
    return subprocess.run([sys.executable, "-c", probe], cwd=ROOT, check=False).returncode == 0


def _refuse_sched_setattr() -> None:
    """In the child before exec: sched_setattr fails with EPERM from here on, for it and
    every process it starts (seccomp filters are inherited; no_new_privs is the price)."""
    libc = ctypes.CDLL(None, use_errno=True)
    program = b"".join(struct.pack("<HBBI", *op) for op in (
        (0x20, 0, 0, 0),  # load seccomp_data.nr
        (0x15, 0, 1, SCHED_SETATTR_X86_64),  # == sched_setattr ?
        (0x06, 0, 0, 0x00050000 | 1),  # SECCOMP_RET_ERRNO | EPERM
        (0x06, 0, 0, 0x7FFF0000)))  # SECCOMP_RET_ALLOW
    buffer = ctypes.create_string_buffer(program)

    class Fprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    fprog = Fprog(len(program) // 8, ctypes.addressof(buffer))
    if libc.prctl(38, 1, 0, 0, 0) != 0 or libc.prctl(22, 2, ctypes.byref(fprog), 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "seccomp filter not installed")


@contextlib.contextmanager
def modbus_plc(tmp_path: Path, preexec: Callable[[], None] | None = None
               ) -> Iterator[tuple[subprocess.Popen[str], int, int, Path]]:
    """`softplc run` with Modbus and HTTP: (process, Modbus port, HTTP port, its stderr)."""
    modbus, api = free_port(), free_port()
    stderr_path = tmp_path / "stderr.txt"
    with stderr_path.open("w") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
             "--modbus", f"127.0.0.1:{modbus}", "--api", f"127.0.0.1:{api}", "--opcua", "off",
             "--state-dir", str(tmp_path / "state"), "--quiet", "--period", "10ms"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=stderr, text=True,
            preexec_fn=preexec)
    try:
        yield proc, modbus, api, stderr_path
    finally:
        stop_process(proc)


def test_only_the_modbus_process_asks_for_a_slice_of_its_own() -> None:
    groups = service_groups(CommConfig(modbus=("127.0.0.1", 1), api=("127.0.0.1", 2),
                                       opcua=("127.0.0.1", 3), modbus_tls=("127.0.0.1", 4)))
    assert {name: group.slice_ns for name, group in groups.items()} == {
        "modbus": MODBUS_SLICE_NS, "modbus-tls": 0, "http": 0, "opcua": 0}


def test_a_process_that_is_gone_is_a_refusal_in_words_not_an_exception() -> None:
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait(30)
    answer = request_slice(MODBUS_SLICE_NS, ended.pid)
    assert not answer.ok and answer.refused
    assert "refused" in answer.words() and "base slice" in answer.words()


def test_a_kernel_that_reads_back_another_slice_is_said_not_to_take_it() -> None:
    answer = SliceAnswer(MODBUS_SLICE_NS, {1: 0, 2: 0})
    assert not answer.ok and "not taken" in answer.words()
    clamped = SliceAnswer(20_000, {1: 100_000})  # the kernel's range starts at 0.1 ms
    assert clamped.ok and "0.1 ms on 1 thread" in clamped.words()


def test_a_real_time_thread_keeps_its_policy_and_the_others_get_the_slice() -> None:
    if not _kernel_takes_slices():
        pytest.skip(f"this kernel ({platform.release()}) has no custom slices (Linux 6.12+)")
    child = """
import json, os, threading
from softplc.runtime.serve.timeslice import request_slice
ready, done = threading.Event(), threading.Event()
def fifo():
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        print(json.dumps(None)); os._exit(0)
    ready.set(); done.wait(30)
thread = threading.Thread(target=fifo); thread.start(); ready.wait(30)
answer = request_slice(100_000)
print(json.dumps([answer.ok, sorted(answer.granted_ns), thread.native_id, os.getpid(),
                  os.sched_getscheduler(thread.native_id) == os.SCHED_FIFO]))
done.set()
"""
    out = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=True).stdout
    if json.loads(out) is None:
        pytest.skip("SCHED_FIFO refused here (no CAP_SYS_NICE)")
    ok, granted, fifo_tid, main_tid, still_fifo = json.loads(out)
    assert ok and granted == [main_tid] and fifo_tid not in granted and still_fifo


def test_the_modbus_process_runs_with_its_slice_on_every_thread(tmp_path: Path) -> None:
    if not _kernel_takes_slices():
        pytest.skip(f"this kernel ({platform.release()}) has no custom slices (Linux 6.12+)")
    with modbus_plc(tmp_path) as (proc, modbus, api, _):
        wait_for(lambda: scan_count(modbus), what="Modbus answers")
        pids = {name: wait_for(lambda port=port: listener(proc.pid, port),  # type: ignore[misc]
                               what=f"the process listening on {port}")
                for name, port in (("modbus", modbus), ("http", api))}
        tids = {name: [int(t.name) for t in Path(f"/proc/{pid}/task").iterdir()]
                for name, pid in pids.items()}
        slices = {name: {slice_of(tid) for tid in found} - {None}
                  for name, found in tids.items()}
        base = slice_of(proc.pid)
    assert slices["modbus"] == {MODBUS_SLICE_NS}, slices
    assert slices["http"] == {base} and base != MODBUS_SLICE_NS, (slices, base)


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the seccomp filter names x86_64's "
                    "syscall number")
def test_a_refused_slice_is_one_log_line_and_modbus_serves(tmp_path: Path) -> None:
    with modbus_plc(tmp_path, preexec=_refuse_sched_setattr) as (proc, modbus, _, stderr):
        first = wait_for(lambda: scan_count(modbus), what="Modbus answers")
        wait_for(lambda: ((n := scan_count(modbus)) is not None and n > first) or None,
                 what="Modbus serves newer scans")
        pid = wait_for(lambda: listener(proc.pid, modbus), what="the Modbus process")
        assert slice_of(pid) != MODBUS_SLICE_NS  # the base slice: the filter held
        assert proc.poll() is None
    lines = [line for line in stderr.read_text().splitlines() if "scheduler slice" in line]
    assert lines == ["softplc-modbus: scheduler slice 0.1 ms refused (Operation not "
                     "permitted); the base slice"], stderr.read_text()
