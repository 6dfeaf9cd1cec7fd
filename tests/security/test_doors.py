"""Every door goes through the security model's decision points (issue 38).

A door is code that lets a client download, write, force, change the state or pause: it
reaches the scan through the channel (`send_command`, `send_hmi_write`, a CommandRequest or an
HmiWrite made for it). This test reads every module of softplc (AST) and lists those that do;
each must be a door named below with the decision point it asks, or an in-process caller that
is no door (the simulator, replays, benchmarks, the paper's local device interface). A new
module that reaches the scan fails here until it is listed, and listing it means naming how
it is decided. The HTTP routes and OPC UA methods are enumerated from what the servers serve:
a new route or method without an act fails too.
"""

from __future__ import annotations

import ast
from pathlib import Path

from softplc.api.roles import ROUTE_ACTS, changes_state, route_act
from softplc.api.server import ApiServer
from softplc.opcua.access import METHOD_ACTS
from softplc.opcua.program import COMMANDS
from softplc.opcua.space import METHODS
from softplc.security.roles import COMMAND_ROLES, Act, Role

ROOT = Path(__file__).resolve().parents[2] / "softplc"
SENDS = frozenset({"send_command", "send_hmi_write"})  # the channel's client side
MAKES = frozenset({"CommandRequest", "HmiWrite"})  # a message made for the scan

# module -> (the door, the decision points it asks: names it must call).
DOORS: dict[str, tuple[str, frozenset[str]]] = {
    # HTTP: every route's act decided by accessroutes.admit -> Gate.decide -> Authority.decide
    "api/server.py": ("HTTP middleware", frozenset({"admit"})),
    "api/commands.py": ("HTTP lifecycle commands, behind api/server.py's middleware",
                        frozenset()),
    "api/symbols.py": ("HTTP symbol writes, behind api/server.py's middleware", frozenset()),
    # OPC UA: methods and writes decided per session (opcua/access.py decide), Download's
    # program by the program gate
    "opcua/server.py": ("OPC UA writes and method calls", frozenset({"decide"})),
    "opcua/program.py": ("OPC UA Download", frozenset({"admit"})),
    # Modbus TCP (write policy as a granted role) and Modbus/TCP Security (certificate role)
    "hmi/map.py": ("Modbus TCP writes", frozenset({"granted"})),
    "runtime/serve/comm.py": ("starts the Modbus slaves (hmi/map.py decides their writes)",
                        frozenset()),
    # Sparkplug B (issue 41): a host's NCMD writes and program commands, decided for the
    # door's configured role (--sparkplug-role, default viewer: nothing)
    "sparkplug/door.py": ("Sparkplug NCMD writes and commands", frozenset({"granted"})),
}
# Callers in the PLC's own process or offline tools: no client reaches them.
NOT_DOORS: frozenset[str] = frozenset({
    "runtime/shared/channel.py",  # the channel itself
    "debug/replay.py", "debug/tracewalk.py", "runtime/offline/simscript.py",  # traces, simulate
    "interface/device.py",  # the seed paper's device interface over a local PLC
    "bench/onlinebench.py",  # the online-change benchmark drives its own scan
})


def _reaches_and_calls(tree: ast.AST) -> tuple[bool, set[str]]:
    """Whether a module reaches the scan (refers to the channel's send methods, called or
    handed on: `asyncio.to_thread(channel.send_command, ...)`, or makes a message for it),
    and the names it calls."""
    reaches, called = False, set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            reaches |= node.attr in SENDS
            called.add(node.attr)  # a method handed on to be called counts as called
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else \
                func.id if isinstance(func, ast.Name) else ""
            called.add(name)
            reaches |= name in MAKES
    return reaches, called


def _modules() -> dict[str, tuple[bool, set[str]]]:
    found = {}
    for path in sorted(ROOT.rglob("*.py")):
        rel = str(path.relative_to(ROOT))
        found[rel] = _reaches_and_calls(ast.parse(path.read_text(encoding="utf-8"), rel))
    return found


def test_every_module_that_reaches_the_scan_is_a_listed_door_or_no_door() -> None:
    modules = _modules()
    reaching = {rel for rel, (reaches, _) in modules.items() if reaches}
    unlisted = sorted(reaching - set(DOORS) - NOT_DOORS)
    assert not unlisted, (f"modules reaching the scan without a decision point listed in "
                          f"tests/security/test_doors.py: {unlisted}")
    gone = sorted((set(DOORS) | NOT_DOORS) - reaching)
    assert not gone, f"listed but no longer reaching the scan (strike them off): {gone}"
    for rel, (door, asks) in DOORS.items():
        missing = asks - modules[rel][1]
        assert not missing, f"{rel} ({door}) no longer calls {sorted(missing)}"


def test_every_served_http_route_has_an_act_and_changes_are_never_reads(tmp_path: Path) -> None:
    server = ApiServer(None, None, None, state_dir=tmp_path)  # type: ignore[arg-type]
    served = {("GET" if r.method == "HEAD" else r.method, r.resource.canonical)
              for r in server.build_app().router.routes() if r.resource is not None}
    assert served == set(ROUTE_ACTS)
    for method, route in served:
        act = route_act(method, route)
        if changes_state(method) and act is not None:
            assert act is not Act.READ, f"{method} {route} changes something but is a read"
    assert route_act("POST", "/api/v1/a-route-nobody-listed") is Act.ADMINISTER  # closed


def test_every_opcua_method_has_the_act_of_its_command() -> None:
    assert set(METHODS) == set(METHOD_ACTS) == set(COMMANDS)
    for method, command in COMMANDS.items():
        assert METHOD_ACTS[method] is Act.of(command)


def test_one_role_table_for_every_act() -> None:
    assert set(COMMAND_ROLES) == set(Act)
    assert COMMAND_ROLES[Act.WRITE] is Role.OPERATOR and COMMAND_ROLES[Act.READ] is Role.VIEWER
    assert all(COMMAND_ROLES[act] is Role.ENGINEER for act in (
        Act.DOWNLOAD, Act.FORCE, Act.BREAK, Act.STEP, Act.CONTINUE, Act.KILL, Act.RESET))
