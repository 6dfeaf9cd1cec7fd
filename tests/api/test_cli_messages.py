"""What a person reads from the client commands: each reply names its command and state once,
refusals name the states that would accept the command (docs/operations.md, command contract),
and every option of every subcommand has help text that gives its default."""

from __future__ import annotations

import argparse

import pytest

from softplc.api.clicmds import EXIT_OK, EXIT_REFUSED
from softplc.cli import build_parser, main
from softplc.core.lifecycle import Command, accepting
from tests.api.conftest import ServerThread
from tests.api.helpers import TRANSPORT


def _out(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out.strip(), captured.err.strip()


def test_lifecycle_replies_say_each_thing_once(api: ServerThread,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _out(capsys, "download", str(TRANSPORT), "--api", api.url)
    assert code == EXIT_OK and out == "download: now STOPPED"
    assert _out(capsys, "start", "--api", api.url)[:2] == (EXIT_OK, "start: now RUNNING")
    assert _out(capsys, "stop", "--api", api.url)[:2] == (EXIT_OK, "stop: now STOPPED")
    assert _out(capsys, "reset", "--api", api.url)[:2] == (EXIT_OK, "reset: now STOPPED")
    code, out, _ = _out(capsys, "force", "hold", "1", "--api", api.url)
    assert code == EXIT_OK and out.count("force") == 1 and out.count("STOPPED") == 1, out
    code, out, _ = _out(capsys, "unforce", "--api", api.url)
    assert code == EXIT_OK and out.startswith("unforce: released ") and "unforce" not in out[8:]
    assert out.endswith("(state STOPPED)"), out


def test_refusals_name_the_accepting_states_once(api: ServerThread,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _out(capsys, "stop", "--api", api.url)
    assert code == EXIT_REFUSED
    assert err == ("softplc stop: refused (HTTP 409): stop is not accepted in state EMPTY "
                   f"(accepted in {accepting(Command.STOP)})")
    code, _, err = _out(capsys, "force", "hold", "1", "--api", api.url)
    assert code == EXIT_REFUSED and err.count("refused") == 1, err
    assert f"accepted in {accepting(Command.FORCE)}" in err
    assert _out(capsys, "download", str(TRANSPORT), "--api", api.url)[0] == EXIT_OK
    assert _out(capsys, "start", "--api", api.url)[0] == EXIT_OK
    code, _, err = _out(capsys, "download", str(TRANSPORT), "--api", api.url)
    assert code == EXIT_REFUSED and "accepted in EMPTY, FAULTED, KILLED, STOPPED" in err, err


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:  # type: ignore[type-arg]
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return sub


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return dict(_subparsers(parser).choices)


def test_every_option_has_help_with_its_default() -> None:
    missing = []
    subcommands = _subcommands(build_parser())
    assert {"check", "run", "simulate", "replay", "download", "upload", "status", "reset",
            "force", "unforce"} <= subcommands.keys()
    for name, parser in subcommands.items():
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            label = f"softplc {name} {'/'.join(action.option_strings) or action.dest}"
            if not action.help:
                missing.append(f"{label}: no help text")
                continue
            shown = parser._get_formatter()._expand_help(action)
            has_default = action.default is not None and action.default is not False
            if has_default and action.option_strings and "default" not in shown:
                missing.append(f"{label}: help does not give the default {action.default!r}")
    assert not missing, "\n".join(missing)


def test_lifecycle_help_names_the_accepting_states() -> None:
    summaries = {a.dest: a.help or "" for a in _subparsers(build_parser())._choices_actions}
    for command in ("start", "stop", "resume", "reset", "kill"):
        assert f"(accepted in {accepting(Command(command))})" in summaries[command], command


def test_break_commands_answer_in_the_words_typed(api: ServerThread,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    # before: `break clear` answered "unbreak: removed b1" (the scan's name of the command)
    assert _out(capsys, "download", str(TRANSPORT), "--api", api.url)[0] == EXIT_OK
    assert _out(capsys, "start", "--api", api.url)[0] == EXIT_OK
    for _ in range(2):
        code, out, _ = _out(capsys, "break", "add", "when", "s1_i", "--api", api.url)
        assert code == EXIT_OK and out.startswith("break: "), out
    code, out, _ = _out(capsys, "break", "remove", "b1", "--api", api.url)
    assert (code, out) == (EXIT_OK, "break remove: removed b1 (state RUNNING)")
    code, out, _ = _out(capsys, "break", "clear", "--api", api.url)
    assert (code, out) == (EXIT_OK, "break clear: removed b2 (state RUNNING)")
    assert "unbreak" not in out
