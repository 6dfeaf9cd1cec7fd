"""A download's fate, decided once: the typed verdict the dry run reports and the apply follows.

Owns: `decide` (issue 39, deliver 4): whether a download is accepted in a PLC's stage, and how
(a load from the initial marking, an online change carrying the marking over, a replacement
by another program), or why not, as a `Verdict` (an enum and its reason); the verdict's text
as the dry run says it. The dry run (runtime/prepare.py) and the real apply (core/plc.py)
both call `decide`; nobody parses the text back.
Does not know: the scan, the channel, how a download was compiled or how its plan was built.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from softplc.core import online
from softplc.core.lifecycle import Command, CommandRejected, Stage, accepting, next_stage
from softplc.core.net import CompiledNet, NetState


class Outcome(enum.Enum):
    """What a download does; the first three are accepted."""

    LOAD = "load"  # not RUNNING: loads from its initial marking
    ONLINE_CHANGE = "online change"  # the same program's new version, marking carried over
    REPLACEMENT = "replacement"  # another program while RUNNING, from its initial marking
    REFUSED_SIZES = "refused: sizes"  # its image sizes differ from the runtime's
    REFUSED_STATE = "refused: state"  # the lifecycle table has no download in this stage
    REFUSED_OFFLINE = "refused: offline"  # RUNNING, without online change
    REFUSED_REPLACE = "refused: replace"  # another program on the same devices, no replace
    REFUSED_CARRY = "refused: carry"  # the marking cannot carry over (tokens, timed firing)

    @property
    def accepted(self) -> bool:
        return self in _ACCEPTED


_ACCEPTED = frozenset({Outcome.LOAD, Outcome.ONLINE_CHANGE, Outcome.REPLACEMENT})


@dataclass(frozen=True, slots=True)
class Verdict:
    """`outcome` decides; `reason` says it to people (a refusal's whole reason, as the apply's
    reply gives it; an accepted download's circumstances)."""

    outcome: Outcome
    reason: str
    plan: online.CarryPlan | None = field(default=None, compare=False)  # as checked

    @property
    def accepted(self) -> bool:
        return self.outcome.accepted

    def text(self) -> str:
        """As the dry run says it: `accepted: ...` or `refused: ...`."""
        return f"{'accepted' if self.accepted else 'refused'}: {self.reason}"


def decide(stage: Stage, running: CompiledNet | None, state: NetState | None,
           new: CompiledNet, *, online_change: bool, replace: bool, sizes_fit: bool = True,
           plan: online.CarryPlan | None = None) -> Verdict:
    """The fate of downloading `new` into a PLC in `stage` running `running` with `state`
    (its marking and busy transitions), by the lifecycle table and the online-change rules
    (docs/programs.md, online change). `plan`: the carry plan of `running` -> `new` if one
    was made off the scan (made here otherwise, when needed)."""
    if not sizes_fit:
        return Verdict(Outcome.REFUSED_SIZES, "the program's image sizes differ from the "
                                              "runtime's")
    if stage is not Stage.RUNNING or running is None or state is None:
        try:
            next_stage(stage, Command.DOWNLOAD)
        except CommandRejected as exc:
            return Verdict(Outcome.REFUSED_STATE, exc.reason)
        dropped = " (the marking kept at the stop is dropped)" \
            if stage is Stage.SUSPENDED else ""
        return Verdict(Outcome.LOAD, f"loads from its initial marking ({stage.state.name})"
                                     + dropped)
    if not online_change:
        return Verdict(Outcome.REFUSED_OFFLINE, (
            "download while RUNNING needs online change (--online), or stop the program first "
            "(a plain download is accepted in "
            f"{accepting(Command.DOWNLOAD).replace(', RUNNING', '')})"))
    if new.name == running.name:
        if plan is None or plan.old is not running or plan.new is not new:
            plan = online.plan(running, new)
        why = online.refusal(plan, state)
        if why is not None:
            return Verdict(Outcome.REFUSED_CARRY, why)
        return Verdict(Outcome.ONLINE_CHANGE, f"online change of {new.name}, the marking "
                                              "carried over by place name", plan)
    same = tuple(running.io.drivers.values()) == tuple(new.io.drivers.values())
    if same and not replace:
        marked = int(np.count_nonzero(state.marking))
        return Verdict(Outcome.REFUSED_REPLACE, (
            f"online change refused: {new.name} is another program than the running "
            f"{running.name} on the same devices; it would start from its initial marking and "
            f"drop the tokens of {marked} marked place(s). Replace it explicitly "
            "(--replace), or stop first"))
    return Verdict(Outcome.REPLACEMENT, f"replacement of {running.name} by {new.name} from "
                   "its initial marking" + ("" if same else " (reconfiguration: new devices)"))

