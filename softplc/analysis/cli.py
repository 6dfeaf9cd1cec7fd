"""The analysis commands of the CLI: `softplc analyze NET` and `softplc export PROGRAM`, and
the summary `softplc check` prints.

Owns: their arguments, exit codes (analyze: 0 no blocking finding, 1 findings, a bad net
or one too large to analyse, 2 incomplete without findings; export: 0 or 1) and output.
Does not know: how the analysis works.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from softplc.analysis.analyze import DEFAULT_MAX_STATES, SEMANTICS, analyze
from softplc.analysis.gate import GATE_MAX_STATES, Verdict, verdict_of, verify
from softplc.analysis.model import AnalysisNet, TooLarge, from_compiled
from softplc.core.net import CompiledNet
from softplc.core.problems import Problem, ProgramError
from softplc.core.symbols import IoImage
from softplc.program.compiler import compile_file, summarize


def add_analyze(an: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    an.add_argument("net", help="program .yaml or net .pnml")
    an.add_argument("--json", action="store_true", help="print one JSON object")
    an.add_argument("--max-states", type=int, default=DEFAULT_MAX_STATES,
                    help="stop exploring past this many states: result incomplete "
                    f"(default {DEFAULT_MAX_STATES})")
    an.add_argument("--semantics", choices=SEMANTICS, default=None,
                    help="scan (the PLC's: default for programs) or interleaving (classical "
                    "P/T reachability graph: default for bare PNML nets)")
    an.set_defaults(func=cmd_analyze)


def add_export(ex: argparse.ArgumentParser) -> None:
    ex.add_argument("program", help="program file (YAML) to export")
    ex.add_argument("-o", "--output", required=True, help="the .pnml file to write")
    ex.add_argument("--format", choices=("pnml", "plcopen"), default="pnml", help="plcopen: "
                    "a PLCopen XML SFC chart, if the net is one (docs/sfc.md; default: pnml)")
    ex.set_defaults(func=cmd_export)


def _load(path: str) -> tuple[AnalysisNet, bool]:
    """The net and whether it is a program (scan semantics meaningful)."""
    from softplc.sfc.load import is_plcopen  # an SFC chart compiles as a program

    if Path(path).suffix.lower() in (".pnml", ".xml") and not is_plcopen(path):
        from softplc.analysis.pnml import load_for_analysis

        net, compiled = load_for_analysis(path)
        return net, compiled is not None
    return from_compiled(compile_file(path)), True


def cmd_analyze(args: argparse.Namespace) -> int:
    try:
        net, program = _load(args.net)
    except ProgramError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print(f"{args.net}: {len(exc.problems)} problem(s)", file=sys.stderr)
        return 1
    except TooLarge as exc:
        print(exc, file=sys.stderr)
        return 1
    semantics = args.semantics or ("scan" if program else "interleaving")
    verdict = verdict_of(analyze(net, semantics, max(1, args.max_states)))
    assert verdict.analysis is not None  # verdict_of always has one
    if args.json:
        print(json.dumps(verdict.analysis.to_dict() | {"findings": list(verdict.findings),
                                                       "blocking": verdict.blocking}))
    else:
        _print(verdict)
    if verdict.blocking:
        return 1
    return 0 if verdict.analysis.graph.complete else 2


def _print(verdict: Verdict) -> None:
    assert verdict.analysis is not None
    d = verdict.analysis.to_dict()
    conservative = {True: "conservative", False: "not conservative",
                    None: "conservative unknown"}[d["conservative"]]
    print(verdict.summary)
    bounds = ", ".join(f"{k}: {'ω' if v is None else v}" for k, v in d["place_bounds"].items())
    print(f"place bounds: {bounds}")
    print(f"max tokens: {d['max_tokens_place']} in a place, {d['max_tokens_marking']} in a "
          f"marking; {conservative}; "
          f"{len(d['p_invariants'])} P-invariant(s), {len(d['t_invariants'])} T-invariant(s)")
    for finding in verdict.findings:
        print(finding)
    for note in d["notes"]:
        print(f"note: {note}")


def check_summary(net: CompiledNet) -> None:
    """What `softplc check` prints after the program summary: findings are warnings."""
    verdict = verify(net)
    print(verdict.summary)
    for finding in verdict.findings:
        print(f"warning: {finding}")


def check_pnml(path: str, check_devices: Callable[[IoImage], list[Problem]]) -> int:
    """`softplc check NET.pnml`: a net with softplc data is checked as a program (devices by
    `check_devices`, which the caller owns); a bare P/T net gets its size and the summary of
    its interleaving analysis. 0, or 1 for a net that cannot be read."""
    from softplc.analysis.pnml import load_for_analysis

    try:
        net, compiled = load_for_analysis(path)
        problems = [] if compiled is None else check_devices(compiled.io)
    except ProgramError as exc:
        problems = list(exc.problems)
    except TooLarge as exc:
        print(exc, file=sys.stderr)
        return 1
    if problems:
        for problem in problems:
            print(problem, file=sys.stderr)
        print(f"{path}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    if compiled is not None:
        print(summarize(compiled))
        check_summary(compiled)
        return 0
    arcs = int((net.pre > 0).sum() + (net.post > 0).sum() + (net.inhibit > 0).sum())
    print(f"P/T net {net.name} ({path}): {net.n_places} places, {net.n_transitions} "
          f"transitions, {arcs} arcs")
    verdict = verdict_of(analyze(net, "interleaving", GATE_MAX_STATES), gate=True)
    print(verdict.summary)
    for finding in verdict.findings:
        print(f"warning: {finding}")
    for note in net.notes:
        print(f"note: {note}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from softplc.analysis.pnml import export_compiled
    from softplc.analysis.pnml_encode import encoding

    try:
        net = compile_file(args.program)
    except ProgramError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return 1
    out = Path(args.output)
    if args.format == "plcopen":
        from softplc.sfc.export import export_plcopen  # refuses a net that is not an SFC

        try:
            chart = export_plcopen(net, compile_file)
        except ProgramError as exc:
            print(exc, file=sys.stderr)
            return 1
        out.write_text(chart, encoding="utf-8")  # steps, not the net's helper places:
        print(f"{args.program} -> {out}: an SFC of {chart.count('<step ')} steps")
        return 0
    io_ref = os.path.relpath(Path(net.io.path).resolve(), out.resolve().parent)
    # Embedded so that the file analyses wherever it is copied (docs/analysis.md, PNML).
    io_text = Path(net.io.path).read_text(encoding="utf-8")
    out.write_text(export_compiled(net, io_image=io_ref, io_text=io_text), encoding="utf-8")
    print(f"{args.program} -> {out}: {len(net.place_names)} places, "
          f"{len(net.transitions)} transitions")
    for warning in encoding(net).warnings:  # what other tools will not see (pnml_encode.py)
        print(f"warning: {args.program}: {warning}", file=sys.stderr)
    return 0
