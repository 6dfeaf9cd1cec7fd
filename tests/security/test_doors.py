"""Every door goes through the security model's decision points (issue 38).

A door is code that lets a client download, write, force, change the state or pause: it
reaches the scan through the channel (`send_command`, `send_hmi_write`, a CommandRequest or an
HmiWrite made for it). This test reads every module of softplc (AST) and lists those that do;
each must be a door named below with the decision point it asks, or an in-process caller that
is no door (the simulator, replays, benchmarks, the paper's local device interface). A new
module that reaches the scan fails here until it is listed, and listing it means naming how
it is decided. The HTTP routes and OPC UA methods are enumerated from what the servers serve:
a new route or method without an act fails too. Doors whose decision is asked elsewhere
(Modbus/TCP Security's certificate role, the program gate's turn and check at HTTP and OPC UA)
are held to their calls; every HTTP client of softplc (the CLI, the DAP adapter and the debug
room's commands, the remote device interface, benchmarks) is listed, and every request the
API's client and the page (its POSTs, PUTs and DELETEs) make is a served route with an act;
the Sparkplug door's program commands are acts of the one table.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

from softplc.api.openapi import API_PREFIX
from softplc.api.roles import ROUTE_ACTS, changes_state, route_act
from softplc.api.server import ApiServer
from softplc.opcua.access import METHOD_ACTS
from softplc.opcua.program import COMMANDS
from softplc.opcua.space import METHODS
from softplc.security.roles import COMMAND_ROLES, Act, Role
from softplc.sparkplug.door import PROGRAM_COMMANDS

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
# Doors whose decision is asked in another module than the one that reaches the scan: the
# module -> (what it decides for which door, the names it must call). Modbus/TCP Security's
# writes reach the scan through hmi/map.py (the write policy); whether the certificate's
# ModbusRole may write at all is decided in tlspeer.py and asked in secure.py.
DECIDED_ELSEWHERE: dict[str, tuple[str, frozenset[str]]] = {
    "hmi/tlspeer.py": ("Modbus/TCP Security: the certificate's ModbusRole (a granted role)",
                       frozenset({"granted"})),
    "hmi/secure.py": ("Modbus/TCP Security writes: the certificate's role asked per write",
                      frozenset({"may_write"})),
    "api/programs.py": ("HTTP POST /program: the program gate's turn and check",
                        frozenset({"turn", "check", "applied"})),
    "api/signed.py": ("HTTP signed downloads: the program gate", frozenset({"admit", "turn"})),
    "opcua/program.py": ("OPC UA Download: the program gate's turn and check",
                         frozenset({"turn", "admit", "applied"})),
}
# Clients of the HTTP doors (they import the API's client, or speak HTTP themselves): they
# reach the PLC only through served routes, each decided by its act (the routes their paths
# name are checked below); module -> what it is.
HTTP_CLIENTS: dict[str, str] = {
    "api/client.py": "the API's client: every command line, the DAP adapter, remote.py",
    "api/plainhttp.py": "the CLI's plain HTTP transport (api/client.py's)",
    "api/clicmds.py": "softplc status/start/stop/... (the CLI)",
    "debug/dap.py": "the DAP adapter (softplc dap): continue, step, status, symbols, why",
    "debug/dapbreaks.py": "the DAP adapter's breakpoints",
    "debug/dapserve.py": "the DAP adapter's transport",
    "debug/debugcli.py": "softplc why / breakpoints (the debug room's command line)",
    "interface/remote.py": "the seed paper's device interface over HTTP",
    "bench/clibench.py": "benchmark", "bench/onlinebench.py": "benchmark",
    "bench/restartbench.py": "benchmark", "bench/watchdogbench.py": "benchmark",
    "bench/isolationbench.py": "benchmark", "bench/load.py": "benchmark",
    "bench/startbench.py": "benchmark", "bench/webbench.py": "benchmark",
}
_HTTP_IMPORTS = frozenset({"softplc.api.client", "softplc.api.plainhttp", "http.client",
                           "urllib.request"})
_HTTP_NAMES = frozenset({"ClientSession", "HTTPConnection", "HTTPSConnection"})
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


@functools.cache
def _trees() -> dict[str, ast.Module]:
    """Every module of softplc, parsed once for all the tests here."""
    return {str(path.relative_to(ROOT)): ast.parse(path.read_text(encoding="utf-8"),
                                                   str(path))
            for path in sorted(ROOT.rglob("*.py"))}


def _modules() -> dict[str, tuple[bool, set[str]]]:
    return {rel: _reaches_and_calls(tree) for rel, tree in _trees().items()}


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


def _http_client(tree: ast.AST) -> bool:
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module in _HTTP_IMPORTS or any(
                f"{node.module}.{a.name}" in _HTTP_IMPORTS for a in node.names)):
            return True
        if isinstance(node, ast.Import) and any(a.name in _HTTP_IMPORTS for a in node.names):
            return True
        if isinstance(node, ast.Attribute | ast.Name) and \
                (node.attr if isinstance(node, ast.Attribute) else node.id) in _HTTP_NAMES:
            return True
    return False


def test_doors_that_decide_elsewhere_still_ask() -> None:
    modules = _modules()
    for rel, (door, asks) in DECIDED_ELSEWHERE.items():
        assert rel in modules, f"{rel} ({door}) is gone: strike it off or name its successor"
        missing = asks - modules[rel][1]
        assert not missing, f"{rel} ({door}) no longer calls {sorted(missing)}"


def test_every_http_client_is_listed() -> None:
    clients = {rel for rel, tree in _trees().items() if _http_client(tree)}
    assert sorted(clients - set(HTTP_CLIENTS)) == [], \
        "HTTP clients not listed in tests/security/test_doors.py HTTP_CLIENTS"
    assert sorted(set(HTTP_CLIENTS) - clients) == [], "listed but no HTTP client: strike off"


def _route_pattern(route: str) -> re.Pattern[str]:
    parts = re.split(r"\{[^}]*\}", route)
    return re.compile("[^/]+".join(re.escape(p) for p in parts) + "(/.*)?" * (
        route.endswith("/static")))


def _served(method: str, path: str) -> list[tuple[str, str]]:
    """The served routes (method, pattern) that `path` (a `*` for each piece only known when
    sent) may reach."""
    wild = re.compile("[^/]+".join(re.escape(p) for p in path.split("*")))
    return [(m, r) for m, r in ROUTE_ACTS if m == method and (
        _route_pattern(r).fullmatch(path.replace("*", "x"))
        or wild.fullmatch(re.sub(r"\{[^}]*\}", "x", r)))]


def _client_calls() -> list[tuple[str, str, str]]:
    """(where, method, path) of every request api/client.py makes (`_json`, `_open`) and the
    page makes (app.js `api(...)`, `fetch(API + ...)`): paths under /api/v1, a dynamic piece
    as `*`."""
    calls: list[tuple[str, str, str]] = []
    tree = ast.parse((ROOT / "api" / "client.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                node.func.attr in ("_json", "_open") and len(node.args) >= 2:
            method, path = node.args[0], node.args[1]
            if isinstance(method, ast.Constant):
                for text in _texts(path):
                    calls.append(("api/client.py", str(method.value), API_PREFIX + text))
    for script in sorted((ROOT / "api" / "static").glob("*.js")):
        source = script.read_text(encoding="utf-8")
        for method, path in re.findall(r'\bapi\("([A-Z]+)", *"([^"]*)"', source):
            calls.append((script.name, method, API_PREFIX + path + ("*" if path.endswith("/")
                                                                     else "")))
        for path, rest in re.findall(r'fetch\(API \+ "([^"]*)"([^)]*)\)', source):
            found = re.search(r'method: *"([A-Z]+)"', rest)
            calls.append((script.name, found.group(1) if found else "GET", API_PREFIX + path))
    return calls


def _texts(node: ast.expr) -> list[str]:
    """The paths an argument may be: a constant, an f-string (its fields `*`), either side of
    a conditional."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, ast.JoinedStr):
        return ["".join(v.value if isinstance(v, ast.Constant) else "*" for v in node.values)]
    if isinstance(node, ast.IfExp):
        return _texts(node.body) + _texts(node.orelse)
    raise AssertionError(f"a path api/client.py builds otherwise: {ast.unparse(node)}")


def test_every_request_of_the_client_and_the_page_is_a_served_decided_route() -> None:
    calls = _client_calls()
    assert {w for w, _, _ in calls} == {"api/client.py", "app.js", "account.js", "timeline.js"}
    changes = [(w, m, p) for w, m, p in calls if changes_state(m)]
    assert any(w == "app.js" for w, _, _ in changes), "the page's POSTs were not found"
    for where, method, path in calls:
        routes = _served(method, path)
        assert routes, f"{where}: {method} {path} is no served route (tests/security)"
        for route in routes:  # every one has an act, or is public by the table
            assert route in ROUTE_ACTS
            if changes_state(method) and ROUTE_ACTS[route] is not None:
                assert ROUTE_ACTS[route] is not Act.READ, f"{where}: {method} {route}"


def test_the_sparkplug_doors_commands_are_acts() -> None:
    assert set(PROGRAM_COMMANDS) == {"start", "stop", "resume", "reset"}
    for command in PROGRAM_COMMANDS.values():
        assert Act.of(command) in COMMAND_ROLES and Act.of(command) is not Act.READ
