"""What each stage of a download does (the job that steps them: runtime/download.py):
compile and analyse (in the compile process, runtime/compileproc.py, or here on a virtual
clock), load the net and build its engine and carry plan a step at a time (`finishing`), open
new devices and stage the boot program (`opening`, the part that blocks); and the dry run,
which says what a download would do and applies nothing.

Owns: where a plain-text download resolves its files (the programs directory) and where a
bundle is unpacked; the analysis gate (docs/analysis.md) and its size bound; refusal texts
with paths as the sender knows them.
Does not know: the scan loop, the channel, the clock.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from softplc.core import online, verdict
from softplc.core.engine import Engine
from softplc.core.errors import SoftplcError
from softplc.core.image import ImageSizes
from softplc.core.lifecycle import PlcState, Stage
from softplc.core.net import CompiledNet, NetState
from softplc.core.plc import Plc
from softplc.core.problems import Problem, ProgramError
from softplc.core.snapshot import CommandReply, CommandRequest
from softplc.core.steps import Steps, drain
from softplc.devices.driver import DeviceError, Driver
from softplc.program import boot, wire
from softplc.program import bundle as bundles
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime import netview
from softplc.runtime.config import LoopConfig
from softplc.runtime.runner import open_drivers

GATE_MAX_TRANSITIONS = 2_000  # larger nets are not analysed on download (see _analyse)


class AnalysisRefused(SoftplcError):
    """A download the analysis gate refuses (--verify refuse): every blocking finding."""

    def __init__(self, findings: tuple[str, ...]) -> None:
        super().__init__("\n".join(findings))
        self.findings = findings


class DownloadRefused(SoftplcError):
    """A download refused for a reason its message says whole (not its program's problems)."""


class CompilerFailed(DownloadRefused):
    """The compile process failed a download for another reason than its program: it died,
    ran past its time, or the compiler raised an internal error."""


@dataclass(frozen=True, slots=True)
class Built:
    """What the compile process sends back for a valid program: the net as bytes
    (program/wire.py), the analysis gate's summary, and the folders bundles were unpacked in
    (stripped from messages)."""

    net: tuple[wire.Piece, ...]
    analysis: dict[str, Any] | None
    bundle_roots: tuple[str, ...] = ()
    boot_file: bytes | None = None  # the boot program's file, encoded (Preparer.build)


class Remote(Protocol):
    """Compiles and analyses a download elsewhere (runtime/compileproc.py). Raises
    ProgramError, AnalysisRefused or CompilerFailed."""

    def build(self, req: CommandRequest) -> Built: ...


@dataclass(slots=True)
class Prepared:
    """A download compiled and its devices opened off the scan: the scan only swaps. `drivers`
    is None when the program's io image declares the drivers already running."""

    net: CompiledNet
    request: CommandRequest
    drivers: list[Driver] | None = None
    engine: Engine | None = None  # the engine's tables for `net`
    plan: online.CarryPlan | None = None  # the marking's carry-over from the running net
    analysis: dict[str, Any] | None = None  # the gate's summary and findings
    staged: Path | None = None  # the next boot program, written, not yet in force
    boot_program: boot.BootProgram | None = None  # what `staged` holds, to put in force
    boot_file: bytes | None = None  # its file, encoded by the compile process (Built)

    def telling(self, reply: CommandReply) -> CommandReply:
        """`reply`, when it is this download's, with what the analysis gate found."""
        found = self.analysis["findings"] if self.analysis else None
        if not found or reply.id != self.request.id:
            return reply
        assert self.analysis is not None
        return CommandReply(reply.id, reply.ok, f"{reply.message}; {self.analysis['summary']} "
                            f"({len(found)} finding(s), see status)", reply.state, reply.expired)

    def close_drivers(self) -> None:
        """Its devices closed: opened for nothing (another download changed the devices)."""
        for driver in self.drivers or ():
            driver.close()
        self.drivers = None

    def discard(self) -> None:
        """Not applied: its devices closed, its staged boot program removed."""
        self.close_drivers()
        if self.staged is not None:
            boot.unstage(self.staged)
            self.staged = None


class Preparer:
    """Prepares downloads for one scan loop. `running` gives the net the PLC runs now and
    `running_specs` the driver specs open now (both read on the scan thread, between scans)."""

    def __init__(self, config: LoopConfig, running: Callable[[], CompiledNet | None],
                 running_specs: Callable[[], tuple[object, ...]],
                 remote: Remote | None = None) -> None:
        self.config = config
        self._running = running
        self._running_specs = running_specs
        self.remote = remote  # compiles in another process; None: on the calling thread
        # Stages an accepted download as the next boot program (runtime/bootkeeper.py), on the
        # download's helper thread; raises OSError when it cannot be kept.
        self.keep: Callable[[Prepared], None] | None = None
        self.bundle_roots: set[str] = set()  # unpacked bundles, stripped from messages

    def relative(self, message: str) -> str:
        """Paths in a message as the sender knows them: relative to the programs' root, never
        the server's absolute paths."""
        root = Path(self.config.root).resolve() if self.config.root else Path.cwd()
        for directory in self.bundle_roots:  # a bundle's files: named as in the bundle
            message = message.replace(f"{directory}/", "")
        return message.replace(f"{root}/", "")

    def compile(self, req: CommandRequest) -> CompiledNet:
        if req.bundle is not None:
            return self.compile_bundle(req.bundle)
        root = Path(self.config.root) if self.config.root else None
        name = req.program_path or "downloaded.yaml"
        if req.program_text is None:
            return compile_file(name, root)
        try:
            return compile_text(req.program_text, self.download_name(name), root)
        except ProgramError as exc:
            if not any("cannot read" in p.message for p in exc.problems):
                raise
            hint = Problem(self.download_name(name), 0, "", (
                "a program sent as plain text resolves io_image: and subnets against the "
                f"server's programs directory {self.programs_dir()} (softplc run "
                "--programs-dir); send a bundle instead (softplc download builds one)"))
            raise ProgramError([*exc.problems, hint]) from None

    def programs_dir(self) -> Path:
        if self.config.programs_dir:
            return Path(self.config.programs_dir).resolve()
        root = Path(self.config.root) if self.config.root else Path.cwd()
        return (root / "programs").resolve()

    def download_name(self, name: str) -> str:
        return str(self.programs_dir() / Path(name).name) if not Path(name).is_absolute() \
            else name

    def _bundle_dir(self, bundle: bundles.Bundle) -> Path:
        """Where a bundle is unpacked: the state dir (it is the boot program's home), else a
        directory of this process's temporary files."""
        base = Path(self.config.state_dir) / "bundles" if self.config.state_dir else \
            Path(tempfile.gettempdir()) / f"softplc-bundles-{os.getpid()}"
        return base / bundle.digest[:16]

    def compile_bundle(self, blob: bytes) -> CompiledNet:
        """Unpack (off the scan) and compile with the bundle's folder as the root: its files
        may reference one another, nothing outside it."""
        try:
            bundle = bundles.unpack(blob)
        except bundles.BundleError as exc:
            raise ProgramError([Problem("bundle", 0, "", str(exc))]) from None
        directory = self._bundle_dir(bundle)
        program = bundles.extract(bundle, directory)
        self.bundle_roots.add(str(directory.resolve()))
        return compile_file(program, directory.resolve())

    def build(self, req: CommandRequest) -> Built:
        """Compile and analyse: what the compile process does for each download."""
        net = self.compile(req)
        analysis = self.analyse(net)
        # The boot program's file encoded here too: JSON-escaping a 500 KB program on a
        # thread of the scan process held the scan's interpreter lock 1-1.5 ms at a time.
        program = self.boot_program(req, net) if self.config.state_dir and not req.dry_run \
            else None
        return Built(wire.dumps(net), analysis, tuple(sorted(self.bundle_roots)),
                     None if program is None else boot.encode(program))

    def boot_program(self, req: CommandRequest, net: CompiledNet) -> boot.BootProgram | None:
        """What keeps `req`'s program as the boot program (None: nothing to keep)."""
        if req.bundle is not None:
            # Its text and folder are in the bundle, unpacked again when it boots.
            return boot.BootProgram(net.source, "", None, req.bundle, net.program_hash)
        if req.program_text is not None:
            name = self.download_name(req.program_path or "downloaded.yaml")
            return boot.BootProgram(name, req.program_text, self.config.root, None,
                                    net.program_hash)
        return None

    def opening(self, prepared: Prepared) -> Callable[[], None] | None:
        """What must block before `prepared` can be swapped in, as one piece of work for the
        download's helper thread: the devices its io image declares opened when they are not
        the running ones, so that a program whose devices cannot be opened is refused before
        anything changes (the reconfiguration of the seed paper, checked), and the program
        staged as the next boot program (`keep`), so that a download the PLC could not keep
        across a restart is refused too. None: nothing to do (a dry run opens nothing)."""
        if prepared.request.dry_run:
            return None
        specs = tuple(prepared.net.io.drivers.values())
        new_devices = specs != self._running_specs()
        keep = self.keep
        if not new_devices and keep is None:
            return None

        def work() -> None:
            if keep is not None:
                keep(prepared)
            if new_devices:
                prepared.drivers = open_drivers(prepared.net.io, self.config.seed, None)
        return work

    def finishing(self, req: CommandRequest, net: CompiledNet | tuple[wire.Piece, ...],
                  analysis: dict[str, Any] | None, boot_file: bytes | None = None
                  ) -> Steps[Prepared]:
        """Everything the swap needs, a step at a time: the net loaded (when it came as bytes
        from the compile process: every expression compiled again from its text by the
        sandboxed compiler, ~50 ms for 10,000 transitions), the engine's tables primed on its
        initial marking (the swap scan then re-checks only what the carried marking changes)
        and the carry plan against the net running now (the scan checks it still is)."""
        if isinstance(net, tuple):
            net = yield from wire.loading(net)
        engine = yield from Engine.stepwise(net, NetState.initial(net))
        yield from engine.priming()
        if not req.dry_run:  # what its board shows, described before its swap scan
            yield
            netview.prewarm(net)
        running = self._running()
        plan = (yield from online.planning(running, net)) if running is not None \
            and (running.name == net.name or req.dry_run) else None
        return Prepared(net, req, None, engine, plan, analysis, boot_file=boot_file)

    def replanning(self, prepared: Prepared) -> Steps[None] | None:
        """The carry plan of a download made again, a step at a time, when the net running
        now is not the one it was planned against (another download was applied since); None
        when it holds or none is needed (a replacement carries nothing)."""
        running, net = self._running(), prepared.net
        if running is None or running.name != net.name or (
                prepared.plan is not None and prepared.plan.old is running):
            return None

        def steps() -> Steps[None]:
            prepared.plan = yield from online.planning(running, net)
        return steps()

    def analyse(self, net: CompiledNet, gate: bool = True) -> dict[str, Any] | None:
        """The analysis gate (docs/analysis.md), off the scan. Refuses by raising
        AnalysisRefused under --verify refuse (when `gate`); otherwise the findings go along."""
        if self.config.verify == "off":
            return None
        if len(net.transitions) > GATE_MAX_TRANSITIONS:
            # Exploring a state space per download must stay a matter of seconds: beyond this
            # size it is `softplc analyze`'s job, offline. Under refuse, what was not verified
            # is not accepted.
            why = (f"{self.relative(net.source)}:1: not analysed: {len(net.transitions)} "
                   f"transitions exceed the download gate's {GATE_MAX_TRANSITIONS} (run "
                   "`softplc analyze` on it offline)")
            if gate and self.config.verify == "refuse":
                raise AnalysisRefused((why,))
            return {"summary": "analysis skipped (net too large for the download gate)",
                    "blocking": False, "findings": [why], "policy": self.config.verify}
        from softplc.analysis.gate import verify

        verdict = verify(net)
        if gate and verdict.blocking and self.config.verify == "refuse":
            raise AnalysisRefused(tuple(self.relative(f) for f in verdict.findings))
        return {"summary": verdict.summary, "blocking": verdict.blocking,
                "findings": [self.relative(f) for f in verdict.findings],
                "policy": self.config.verify}


@dataclass(frozen=True, slots=True)
class Boundary:
    """The PLC as a dry run's answer reads it, copied at the scan boundary where its turn came
    (the marking array, the token lists, the busy transitions: microseconds), so that the
    answer can be built between the scans that follow."""

    net: CompiledNet | None
    net_state: NetState | None  # without its enabling timers: the answer does not read them
    state: PlcState
    stage: Stage
    sizes: ImageSizes


def boundary(plc: Plc, sizes: ImageSizes) -> Boundary:
    """`plc` now, for a dry run's answer (on the scan thread, at a scan boundary)."""
    copy = None
    if plc.net is not None and plc.engine is not None:
        live = plc.engine.state
        copy = NetState(live.marking.copy(), {p: list(t) for p, t in live.tokens.items()},
                        {}, dict(live.busy))
    return Boundary(plc.net, copy, plc.state, plc.stage, sizes)


def dry_run(plc: Plc, prepared: Prepared, sizes: ImageSizes) -> CommandReply:
    """What the download would do now, against the running state; nothing applied."""
    return drain(answering(prepared, boundary(plc, sizes)))


def answering(prepared: Prepared, at: Boundary) -> Steps[CommandReply]:
    """A dry run's reply, a step at a time (the job steps it between scans: the carry plan
    again when another net runs since it was made, the plan described, the verdict), against
    the PLC as it was at the boundary `at`; nothing applied."""
    net, req = prepared.net, prepared.request
    if at.net is None or at.net_state is None:
        marked = np.flatnonzero(net.initial)
        taken = yield from online.driving(net)
        detail: dict[str, Any] = {
            "from": None, "to": net.name, "replacement": False, "kept": {}, "dropped": {},
            "new": (yield from online.counting(net, net.initial, marked)), "records": {},
            "outputs": {"released": [], "taken": sorted(taken)}}
    else:
        carry_plan = prepared.plan if prepared.plan is not None \
            and prepared.plan.old is at.net else (yield from online.planning(at.net, net))
        detail = yield from online.describing(carry_plan, at.net_state)
        prepared.plan = carry_plan
    fate = decision(prepared, at)
    detail["verdict"], detail["accepted"] = fate.text(), fate.accepted
    detail["outcome"] = fate.outcome.value
    detail["state"] = at.state.name
    prepared.discard()
    return CommandReply(req.id, True, f"dry run: {detail['verdict']} (nothing applied)",
                        at.state, detail=detail)


def decision(prepared: Prepared, at: Boundary) -> verdict.Verdict:
    """The download's fate in the state at `at`: the `decide` of the real apply
    (core/verdict.py), on the plan made off the scan when it still holds."""
    net, req = prepared.net, prepared.request
    plan = prepared.plan if prepared.plan is not None and prepared.plan.old is at.net else None
    return verdict.decide(at.stage, at.net, at.net_state, net, online_change=req.online,
                          replace=req.replace, sizes_fit=net.io.sizes == at.sizes, plan=plan)


def describe_error(error: BaseException) -> str:
    """A refused download's reason in one line: a device, or an internal compiler error."""
    if isinstance(error, DownloadRefused):
        return str(error)
    if isinstance(error, DeviceError | ValueError | OSError):
        return f"its devices cannot be opened: {error}"
    return f"internal compiler error ({type(error).__name__}: {error})"
