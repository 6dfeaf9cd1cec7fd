"""Standard function block instances in a chart: TON, TOF, TP, R_TRIG, F_TRIG (IEC 61131-3).

Owns: what a call `T1(IN := expr, PT := T#5s);` in an ST action body becomes, and how an
instance's state lives in the net (docs/sfc.md, "Function blocks"). An instance is memory
BOOLs `T1_IN` (the IN of the last call), `T1_Q` (Q as the last call computed it) and, for
the timers, `T1_done` (the time has run out) and, for TP, `T1_B` (a pulse started and not
yet re-armed); R_TRIG/F_TRIG keep `T1_M` (IEC's M). A call is one simultaneous update of
that state from IN and the old state (its statements are grouped: each reads the values
from before the call, `&` marks the group's later statements for emit.sequential); Q is
written only by a call, so an instance not called keeps its outputs. The time is one
always-marked place `T1_timer` with two self-loops: `T1_elapsed` (`delay:` PT, guard the
timer's running condition, sets `T1_done`) and `T1_rearm` (resets `T1_done` once the
condition is gone); softplc's enabling delay restarting when its guard goes false is the
timer's reset. Running condition: TON IN, TOF NOT IN AND Q, TP Q.
Does not know: ST parsing (st.py hands it the emitted IN text), YAML, XML.
"""

from __future__ import annotations

from softplc.core.errors import SoftplcError
from softplc.core.problems import Problem
from softplc.sfc.model import Chart, Transition, Variable

TIMERS = ("TON", "TOF", "TP")
TRIGGERS = ("R_TRIG", "F_TRIG")
SUPPORTED = "TON, TOF, TP (inputs IN, PT; output Q), R_TRIG, F_TRIG (input CLK; output Q)"
PT_MARK = "#"  # a statement `#T1_PT = 5000` carries PT to emit.py; it writes nothing


class FbError(SoftplcError, ValueError):
    """A call or a use outside what maps; `offset` is where in the ST text."""

    def __init__(self, message: str, offset: int) -> None:
        super().__init__(message, offset)
        self.message, self.offset = message, offset


def fb_type(kind: str) -> str:
    """The FB type of a variable kind `fb:TON` ("" when not an FB instance)."""
    return kind[3:] if kind.startswith("fb:") else ""


def supported(kind: str) -> bool:
    return fb_type(kind) in (*TIMERS, *TRIGGERS)


def refuse_type(inst: str, kind: str, offset: int) -> FbError:
    return FbError(f"{inst} is an instance of {fb_type(kind) or 'a derived type'}: function "
                   f"blocks supported: {SUPPORTED}; anything else (CTU, SR, user-defined "
                   "function blocks) is refused", offset)


def output(inst: str, kind: str, field: str, offset: int) -> str:
    """The memory symbol `inst.field` reads (BOOL)."""
    if not supported(kind):
        raise refuse_type(inst, kind, offset)
    if field == "Q":
        return f"{inst}_Q"
    if field == "ET" and fb_type(kind) in TIMERS:
        raise FbError(f"{inst}.ET: the elapsed time needs a clock that softplc's expressions "
                      "do not read (a timer is a net delay); compare with Q, or use "
                      "`Step.T >= T#...`", offset)
    raise FbError(f"{inst}.{field}: only the output Q of a {fb_type(kind)} is read "
                  f"(supported: {SUPPORTED})", offset)


def state(typ: str) -> list[str]:
    """The memory BOOLs of one instance, by suffix."""
    if typ in TRIGGERS:
        return ["M", "Q"]
    return ["IN", "Q", "done", *(["B"] if typ == "TP" else [])]


def running(typ: str, inst: str) -> str:
    """The condition the timer's time runs under (softplc expression on the state)."""
    return {"TON": f"{inst}_IN", "TOF": f"(not {inst}_IN and {inst}_Q)",
            "TP": f"{inst}_Q"}[typ]


def expand(inst: str, kind: str, args: dict[str, tuple[str, str, int]],
           offset: int) -> list[tuple[str, str, str]]:
    """A call with formal arguments {PARAM: (softplc text, kind, offset)} -> the statements
    (target, kind, softplc text) it is; grouped targets start with `&`."""
    typ = fb_type(kind)
    if not supported(kind):
        raise refuse_type(inst, kind, offset)
    inputs = ("CLK",) if typ in TRIGGERS else ("IN", "PT")
    for name, (_text, _kind, at) in args.items():
        if name not in inputs:
            raise FbError(f"{inst}({name} := ...): {typ} has the inputs "
                          f"{', '.join(inputs)}", at)
    x = f"{inst}_"
    if typ in TRIGGERS:
        last = f"{x}M" if typ == "R_TRIG" else f"(not {x}M)"  # no CLK: the last CLK
        e = _bool(args["CLK"], f"{inst}.CLK") if "CLK" in args else last
        if typ == "R_TRIG":  # IEC: Q := CLK AND NOT M; M := CLK;
            return [(f"{x}Q", "bool", f"({e} and not {x}M)"), (f"&{x}M", "bool", e)]
        return [(f"{x}Q", "bool", f"((not {e}) and not {x}M)"),  # F_TRIG: M := NOT CLK
                (f"&{x}M", "bool", f"(not {e})")]
    e = _bool(args["IN"], f"{inst}.IN") if "IN" in args else f"{x}IN"  # none: the last IN
    out = _timer(typ, x, e)
    if "PT" in args:
        text, pk, at = args["PT"]
        if pk != "time" or not text.isdigit() or int(text) <= 0:
            raise FbError(f"{inst}(PT := {text}): PT must be a positive TIME literal "
                          "(T#5s): the timer is a net delay, fixed when the chart is "
                          "compiled", at)
        out.append((f"{PT_MARK}{x}PT", "time", text))
    return out


def _bool(arg: tuple[str, str, int], what: str) -> str:
    text, kind, at = arg
    if kind != "bool" and text not in ("0", "1"):
        raise FbError(f"{what} := {text} is {kind.upper()}, expected BOOL", at)
    return {"0": "false", "1": "true"}.get(text, f"({text})")


def _timer(typ: str, x: str, e: str) -> list[tuple[str, str, str]]:
    """IEC's TON/TOF/TP bodies (matiec's STATE machines) over the memory state; `x_done`
    stands for START_TIME + PT <= CURRENT_TIME."""
    q, old, done = f"{x}Q", f"{x}IN", f"{x}done"
    if typ == "TON":  # Q once IN has held for PT; IN false resets
        return [(q, "bool", f"({e} and {old} and {done})"), (f"&{old}", "bool", e)]
    if typ == "TOF":  # Q on with IN, off PT after IN fell
        return [(q, "bool", f"({e} or ({q} and ({old} or not {done})))"),
                (f"&{old}", "bool", e)]
    b = f"{x}B"  # TP: STATE 1 is Q, STATE 1 or 2 is B; a rising IN starts from STATE 0
    start = f"(not {b} and not {old} and {e})"
    ended = f"(({b} and not {q}) or ({q} and {done}))"
    return [(q, "bool", f"({start} or ({q} and not {done}))"),
            (f"&{b}", "bool", f"({start} or ({b} and not ({ended} and not {e})))"),
            (f"&{old}", "bool", e)]


def instances(chart: Chart) -> list[tuple[Variable, str]]:
    return [(v, fb_type(v.kind)) for v in chart.variables.values() if supported(v.kind)]


def symbols(chart: Chart) -> list[tuple[str, Variable, str]]:
    """(memory BOOL, its instance, suffix) for every supported instance."""
    return [(f"{v.name}_{s}", v, s) for v, typ in instances(chart) for s in state(typ)]


def _calls(chart: Chart, v: Variable) -> list[tuple[int, str]]:
    """(action line, PT text or "") of every call of `v` (found by its grouped IN/M write)."""
    heads = (f"&{v.name}_IN", f"&{v.name}_M")
    out = []
    for a in chart.actions:
        stmts = dict(a.statements)
        if any(h in stmts for h in heads):
            out.append((a.line, stmts.get(f"{PT_MARK}{v.name}_PT", "")))
    return out


def delays(chart: Chart) -> dict[str, int]:
    """PT in ms of every timer instance that is called with one."""
    out = {}
    for v, typ in instances(chart):
        pts = [pt for _, pt in _calls(chart, v) if pt]
        if typ in TIMERS and pts:
            out[v.name] = int(pts[0])
    return out


def places(chart: Chart) -> list[tuple[str, str, int]]:
    return [(f"{v.name}_timer", f"time of {v.name} ({typ}, PT {delays(chart)[v.name]} ms), "
             f"{chart.file}:{v.line}: always marked", v.line)
            for v, typ in instances(chart) if v.name in delays(chart)]


def transitions(chart: Chart) -> list[tuple[Transition, list[tuple[str, str]]]]:
    out = []
    pts = delays(chart)
    for v, typ in instances(chart):
        if v.name not in pts:
            continue
        p, run, done = f"{v.name}_timer", running(typ, v.name), f"{v.name}_done"
        out.append((Transition(f"{v.name}_elapsed", v.line, (p,), (p,), f"{v.name} ({typ}) "
                               f"running for PT", guard=f"{run} and not {done}",
                               delay_ms=pts[v.name]), [(f"set {done}", str(v.line))]))
        out.append((Transition(f"{v.name}_rearm", v.line, (p,), (p,), f"{v.name} ({typ}) "
                               "stopped", guard=f"{done} and not {run}"),
                    [(f"reset {done}", str(v.line))]))
    return out


def check(chart: Chart, problems: list[Problem]) -> None:
    """One calling action per instance (two would run in one round without IEC's order),
    one call of a timer per body, one PT per timer, a PT where a timer is called, no clash
    with a declared name."""
    names = set(chart.variables)
    for v, typ in instances(chart):
        where = f"{v.name} ({typ})"
        for sym in (f"{v.name}_{s}" for s in state(typ)):
            if sym.upper() in names:
                problems.append(Problem(chart.file, v.line, "", f"{where}: its state is kept "
                                f"in {sym}, which the chart also declares; rename one"))
        calls = _calls(chart, v)
        twice = [a.line for a in chart.actions if typ in TIMERS
                 and sum(t == f"&{v.name}_IN" for t, _ in a.statements) > 1]
        if twice:
            problems.append(Problem(chart.file, twice[0], "", f"{where} is called twice in "
                            "one action body: its time is a net delay that sees IN once per "
                            "scan (a fall and a rise within one scan would not restart it); "
                            "call a timer once per body"))
        lines = sorted({line for line, _ in calls})
        if len(lines) > 1:
            problems.append(Problem(chart.file, lines[1], "", f"{where} is called by the "
                            f"actions at lines {', '.join(map(str, lines))}: call an instance "
                            "from one action (one action block association) only"))
        pts = sorted({pt for _, pt in calls if pt})
        if typ in TIMERS and calls and not pts:
            problems.append(Problem(chart.file, calls[0][0], "", f"{where} is called without "
                            "PT: give PT := T#... (a TIME literal) in its call"))
        if len(pts) > 1:
            problems.append(Problem(chart.file, calls[0][0], "", f"{where} is called with "
                            f"PT {' and '.join(pts)} ms: one PT per instance (a net delay)"))
