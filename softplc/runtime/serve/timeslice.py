"""The scheduler slice a process asks for (EEVDF, Linux 6.12 and later).

Owns: asking the kernel, for every thread of a process, for a slice other than the base one
(`sched_setattr`, SCHED_OTHER with `sched_runtime`: EEVDF takes it as the slice request,
0.1-100 ms), reading back what each thread got, and saying so in words. Python has no
wrapper and glibc only from 2.41: a ctypes syscall. A kernel before 6.12 accepts the call
and ignores the field (it reads back 0), a seccomp filter or an unknown machine refuses it:
either way the process runs on with the base slice; nothing here raises.
Does not know: which process serves what (comm.py decides who asks).
"""

from __future__ import annotations

import ctypes
import errno
import functools
import os
import platform
from dataclasses import dataclass
from typing import Final

# (sched_setattr, sched_getattr) by machine; the generic table (arm64, riscv64) shares one.
_SYSCALLS: Final = {"x86_64": (314, 315), "aarch64": (274, 275), "riscv64": (274, 275),
                    "i686": (351, 352), "armv7l": (380, 381), "ppc64le": (355, 356)}
_FAIR: Final = (0, 3, 5)  # SCHED_OTHER, SCHED_BATCH, SCHED_IDLE
_RESET_ON_FORK: Final = 0x01
_REAL_TIME: Final = -1
MIN_SLICE_NS: Final = 100_000  # the kernel clamps a request to this range
MAX_SLICE_NS: Final = 100_000_000


class _SchedAttr(ctypes.Structure):
    """struct sched_attr, SCHED_ATTR_SIZE_VER0 (48 bytes); the kernel checks `size`."""

    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32),
                ("sched_flags", ctypes.c_uint64), ("sched_nice", ctypes.c_int32),
                ("sched_priority", ctypes.c_uint32), ("sched_runtime", ctypes.c_uint64),
                ("sched_deadline", ctypes.c_uint64), ("sched_period", ctypes.c_uint64)]


@dataclass(frozen=True, slots=True)
class SliceAnswer:
    """What the threads of a process got: the slice each runs with now, read back, by thread
    id (0 from a kernel before 6.12), or `refused` naming the first error (the threads
    before it got theirs)."""

    requested_ns: int
    granted_ns: dict[int, int]
    refused: str = ""

    @property
    def ok(self) -> bool:
        wanted = min(max(self.requested_ns, MIN_SLICE_NS), MAX_SLICE_NS)
        return not self.refused and bool(self.granted_ns) and all(
            ns == wanted for ns in self.granted_ns.values())

    def words(self) -> str:
        if self.refused:
            return f"scheduler slice {self.requested_ns / 1e6:g} ms refused ({self.refused}); " \
                   f"the base slice"
        if not self.ok:
            got = sorted(set(self.granted_ns.values()))
            return (f"scheduler slice {self.requested_ns / 1e6:g} ms not taken by this kernel "
                    f"(read back {', '.join(f'{ns / 1e6:g}' for ns in got)} ms; custom slices "
                    f"came with Linux 6.12)")
        granted_ns = next(iter(self.granted_ns.values()))
        return f"scheduler slice {granted_ns / 1e6:g} ms on {len(self.granted_ns)} thread(s)"


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _numbers() -> tuple[int, int] | None:
    return _SYSCALLS.get(platform.machine())


def _read(tid: int) -> _SchedAttr | int:
    """sched_getattr of thread `tid`, or the errno."""
    numbers = _numbers()
    if numbers is None:
        return errno.ENOSYS
    attr = _SchedAttr()
    if _libc().syscall(numbers[1], tid, ctypes.byref(attr), ctypes.sizeof(attr), 0) != 0:
        return ctypes.get_errno()
    return attr


def slice_of(tid: int) -> int | None:
    """The slice thread `tid` runs with (ns; 0 on a kernel without custom slices), None
    when it cannot be read (gone, not in the fair class, unknown machine)."""
    attr = _read(tid)
    if isinstance(attr, int) or attr.sched_policy not in _FAIR:
        return None
    return int(attr.sched_runtime)


def _ask(tid: int, slice_ns: int) -> int:
    """sched_setattr for one thread with its policy, niceness and reset-on-fork as they
    are (the call sets them all); 0, the errno, or _REAL_TIME (left alone: no slice)."""
    attr, numbers = _read(tid), _numbers()
    if isinstance(attr, int) or numbers is None:
        return attr if isinstance(attr, int) else errno.ENOSYS
    if attr.sched_policy not in _FAIR:
        return _REAL_TIME
    new = _SchedAttr(size=ctypes.sizeof(_SchedAttr), sched_policy=attr.sched_policy,
                     sched_flags=attr.sched_flags & _RESET_ON_FORK, sched_nice=attr.sched_nice,
                     sched_runtime=slice_ns)
    if _libc().syscall(numbers[0], tid, ctypes.byref(new), 0) != 0:
        return ctypes.get_errno()
    return 0


def request_slice(slice_ns: int, pid: int | None = None) -> SliceAnswer:
    """Ask for `slice_ns` for every thread of process `pid` (this one by default), as it
    stands: threads started later inherit it from the one that starts them."""
    pid = os.getpid() if pid is None else pid
    try:
        tids = sorted(int(name) for name in os.listdir(f"/proc/{pid}/task"))
    except OSError as exc:
        return SliceAnswer(slice_ns, {}, exc.strerror or str(exc))
    granted: dict[int, int] = {}
    for tid in tids:
        code = _ask(tid, slice_ns)
        if code in (errno.ESRCH, _REAL_TIME):
            continue  # a thread that ended meanwhile, or one the fair class does not run
        if code:
            return SliceAnswer(slice_ns, granted, os.strerror(code))
        granted[tid] = slice_of(tid) or 0
    return SliceAnswer(slice_ns, granted)
