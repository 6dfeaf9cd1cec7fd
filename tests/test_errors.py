"""One root for softplc's own errors (issue 27): every error class softplc defines derives from
SoftplcError, and every one crosses processes whole (the compile process and the channel
pickle them): class, args and attributes, whatever its __init__ takes."""

from __future__ import annotations

import ast
import importlib
import pickle
import pkgutil
from pathlib import Path

import softplc
from softplc.core.errors import SoftplcError
from softplc.core.lifecycle import Command, CommandRejected, PlcState
from softplc.core.problems import FaultCode, PlcFault, Problem, ProgramError
from softplc.runtime.prepare import AnalysisRefused, CompilerFailed

ROOT = Path(softplc.__file__).parent
BUILT_IN = {"Exception", "ValueError", "RuntimeError", "OSError", "TimeoutError", "KeyError",
            "LookupError", "TypeError", "ConnectionError"}


def all_error_classes() -> list[type[BaseException]]:
    for module in pkgutil.walk_packages(softplc.__path__, "softplc."):
        importlib.import_module(module.name)
    found: list[type[BaseException]] = []
    todo = list(Exception.__subclasses__())
    while todo:
        cls = todo.pop()
        todo += cls.__subclasses__()
        if cls.__module__.startswith("softplc."):
            found.append(cls)
    return found


def test_every_error_class_of_softplc_derives_from_the_root() -> None:
    """Read from the source too: a class deriving from a built-in error alone fails here."""
    rogue = []
    for path in ROOT.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef) and node.name != "SoftplcError":
                bases = {b.id for b in node.bases if isinstance(b, ast.Name)}
                if bases and bases <= BUILT_IN:  # built-in errors only: outside the root
                    rogue.append(f"{path.relative_to(ROOT)}: {node.name}")
    assert not rogue, "errors outside the root SoftplcError:\n" + "\n".join(sorted(rogue))
    assert all(issubclass(cls, SoftplcError) for cls in all_error_classes())


def test_every_error_crosses_a_process_whole() -> None:
    for cls in all_error_classes():
        error = cls.__new__(cls, "why")
        error.args = ("why",)
        error.detail = {"n": 1}  # type: ignore[attr-defined]
        back = pickle.loads(pickle.dumps(error))
        assert type(back) is cls and back.args == ("why",) and back.detail == {"n": 1}, cls


def test_errors_with_their_own_arguments_come_back_as_they_were() -> None:
    cases: list[SoftplcError] = [
        ProgramError([Problem("a.yaml", 3, "places.p", "bad"), Problem("b.yaml", 1, "", "x")]),
        AnalysisRefused(("deadlock at the initial marking",)),
        CompilerFailed("the compile process ended"),
        CommandRejected(Command.START, PlcState.EMPTY),
        PlcFault(FaultCode.LIMIT, "too many tokens"),
    ]
    for error in cases:
        back = pickle.loads(pickle.dumps(error))
        assert type(back) is type(error) and str(back) == str(error)
        assert vars(back) == vars(error)
