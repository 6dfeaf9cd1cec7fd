"""One typed verdict for a download (issue 39, deliver 4; core/verdict.py): the dry run's
`accepted` flag and `outcome` come from the same `decide` the real apply follows, never from
the verdict's text. For every case (a load while stopped, an online change, a change whose
marking cannot carry over, a download while RUNNING without --online, another program with
and without --replace, a stage that takes no download, other image sizes), the dry run on a
PLC says exactly what applying the same download to that PLC then does. In process."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, CommandRejected
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.snapshot import CommandRequest
from softplc.core.verdict import Outcome, Verdict
from softplc.program.compiler import compile_file
from softplc.runtime.prepare import Prepared, dry_run

IO = """
symbols:
  go:   {address: '%IX0.0'}
  lamp: {address: '%QX0.0', safe: false}
"""
LINE = """program: line
io_image: io.yaml
places:
  a: {tokens: 1}
  b: {outputs: [lamp]}
transitions:
  t: {from: [a], to: [b], when: go}
"""
NETS = {
    "v1": LINE,
    "v2": LINE.replace("  b: {outputs: [lamp]}\n", "  b: {outputs: [lamp]}\n  c: {tokens: 2}\n"),
    "drops_a": LINE.replace("  a: {tokens: 1}\n", "").replace("from: [a]", "from: [b]"),
    "other": LINE.replace("program: line", "program: other"),
    "small": LINE.replace("io_image: io.yaml", "io_image: small_io.yaml"),
}


@pytest.fixture(scope="module")
def nets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, CompiledNet]:
    base: Path = tmp_path_factory.mktemp("verdict")
    (base / "io.yaml").write_text(IO, encoding="utf-8")
    (base / "small_io.yaml").write_text("image: {words: 512}\n" + IO, encoding="utf-8")
    out = {}
    for name, text in NETS.items():
        (base / f"{name}.yaml").write_text(text, encoding="utf-8")
        out[name] = compile_file(str(base / f"{name}.yaml"))
    return out


def stage(nets: dict[str, CompiledNet], *commands: Command) -> Plc:
    plc = Plc.empty()
    plc.apply(ProgramCommand(Command.DOWNLOAD, nets["v1"]), 0)
    for command in commands:
        plc.apply(ProgramCommand(command), 0)
    return plc


RUNNING = (Command.START,)
CASES: list[tuple[str, tuple[Command, ...], str, bool, bool, Outcome]] = [
    ("load while READY", (), "other", False, False, Outcome.LOAD),
    ("load while SUSPENDED", (Command.START, Command.STOP), "v2", False, False, Outcome.LOAD),
    ("online change", RUNNING, "v2", True, False, Outcome.ONLINE_CHANGE),
    ("tokens would be lost", RUNNING, "drops_a", True, False, Outcome.REFUSED_CARRY),
    ("RUNNING without --online", RUNNING, "v2", False, False, Outcome.REFUSED_OFFLINE),
    ("another program", RUNNING, "other", True, False, Outcome.REFUSED_REPLACE),
    ("another program, --replace", RUNNING, "other", True, True, Outcome.REPLACEMENT),
    ("image sizes", (), "small", False, False, Outcome.REFUSED_SIZES),
]


@pytest.mark.parametrize(("setup", "net", "online", "replace", "outcome"),
                         [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_the_dry_run_says_what_the_apply_then_does(
        nets: dict[str, CompiledNet], setup: tuple[Command, ...], net: str, online: bool,
        replace: bool, outcome: Outcome) -> None:
    plc = stage(nets, *setup)
    sizes = plc.image.sizes
    request = CommandRequest(1, Command.DOWNLOAD, online=online, replace=replace, dry_run=True)
    reply = dry_run(plc, Prepared(nets[net], request), sizes)
    assert reply.detail is not None
    assert reply.detail["outcome"] == outcome.value
    assert reply.detail["accepted"] is outcome.accepted
    text = str(reply.detail["verdict"])
    assert text.startswith("accepted: " if outcome.accepted else "refused: ")
    if outcome is Outcome.REFUSED_SIZES:
        return  # the scan loop refuses those before the PLC sees them (runtime/loop.py)
    applied: Callable[[], str] = lambda: plc.apply(  # noqa: E731
        ProgramCommand(Command.DOWNLOAD, nets[net], online, replace=replace), 0)
    if outcome.accepted:
        applied()
        assert plc.net is nets[net]
    else:
        with pytest.raises(CommandRejected) as refused:
            applied()
        assert refused.value.reason in text  # one reason, one text
        assert plc.net is nets["v1"]


def test_a_stage_that_takes_no_download_is_refused_alike(nets: dict[str, CompiledNet]) -> None:
    """KILLED takes a download in the lifecycle table; the test walks to each stage that does
    not, if any, and checks the dry run refuses as the apply does."""
    plc = stage(nets, Command.START, Command.KILL)
    request = CommandRequest(1, Command.DOWNLOAD, dry_run=True)
    reply = dry_run(plc, Prepared(nets["v2"], request), plc.image.sizes)
    assert reply.detail is not None
    try:
        plc.apply(ProgramCommand(Command.DOWNLOAD, nets["v2"]), 0)
        ok = True
    except CommandRejected:
        ok = False
    assert reply.detail["accepted"] is ok
    assert str(reply.detail["outcome"]) in {o.value for o in Outcome}


def test_the_flag_follows_the_outcome_not_the_words() -> None:
    """What the old parse of the text got wrong: a reason is free text (program and place
    names, a lifecycle message); only the outcome decides."""
    misleading = Verdict(Outcome.ONLINE_CHANGE, "refused-batches kept, online change refused "
                                                "by nobody")
    assert misleading.accepted and misleading.text().startswith("accepted: ")
    refused = Verdict(Outcome.REFUSED_STATE, "accepted in STOPPED, not in KILLED")
    assert not refused.accepted and refused.text().startswith("refused: ")
