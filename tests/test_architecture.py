"""The rooms of softplc and who may import whom (issue 15.1), read from the AST of every module
(imports inside functions count too: a lazy import is still a dependency).

A room is a top-level package of softplc (core, program, devices, ...) or a top-level module
(cli). ALLOWED lists, per room, the rooms it may import; a new upward import fails here. The
room graph must have no cycle; the cycles (strongly connected groups) that remain today are
listed in KNOWN_CYCLES, which must match exactly (a new cycle fails, and so does a removed
one until it is struck off). No module is over MAX_LINES lines but those in LARGE_TODAY, each
of which must still be over it (issue 15.4). Within and across rooms, no two modules may
import each other through any chain, type-only imports (under TYPE_CHECKING) included
(issue 27): a module that needs another's object reads it through a Protocol of its own or a
value it is handed.
"""

from __future__ import annotations

import ast
from pathlib import Path

import softplc

ROOT = Path(softplc.__file__).parent

ALLOWED: dict[str, frozenset[str]] = {
    "core": frozenset(),
    # The security model of every door (issue 38): no room imports api to learn who may do
    # what; security imports only core.
    "security": frozenset({"core"}),
    # program/compiler.compile_file is the one door for PLCopen XML charts (issue 42): it
    # imports sfc, which imports only core (the compiler is handed to it as a callable).
    "program": frozenset({"core", "sfc"}),
    "sfc": frozenset({"core"}),
    "analysis": frozenset({"core", "program", "sfc"}),  # sfc: tell a chart from PNML
    "devices": frozenset({"core", "program"}),
    "hmi": frozenset({"core", "security"}),
    # The services meet the runtime through core/snapshot.py (SnapshotSource, the channel's
    # exceptions) and are handed its objects; they never import it.
    "api": frozenset({"core", "program", "security"}),
    # hmi.admission: one connection rule
    "opcua": frozenset({"core", "devices", "hmi", "security"}),
    "runtime": frozenset({"analysis", "api", "core", "devices", "hmi", "opcua", "program",
                          "security"}),
    "interface": frozenset({"api", "core", "devices", "program", "runtime"}),
    # The debugger (issue 40.5): an HTTP client of the API through its public names (see
    # test_no_room_imports_another_rooms_private_names) and offline trace walking over the
    # runtime's trace and replay. No room but cli imports it: the scan process never loads it.
    "debug": frozenset({"api", "core", "devices", "program", "runtime"}),
    # The Sparkplug edge node (issue 41): a service process over the runtime's snapshot; the
    # supervisor starts it from its configuration's `main`, never importing it.
    "sparkplug": frozenset({"core", "runtime", "security"}),
    "bench": frozenset({"analysis", "api", "core", "opcua", "program", "runtime", "security",
                        "sparkplug"}),
    "cli": frozenset({"analysis", "api", "bench", "core", "debug", "devices", "interface",
                      "program", "runtime", "security", "sparkplug"}),
}
# Cycles left to untangle: none (issue 15.1). A new one fails until it is removed or listed.
KNOWN_CYCLES: set[frozenset[str]] = set()


# Circles between modules (issue 27): none left. A new one fails until it is untangled.
KNOWN_MODULE_CYCLES: set[frozenset[str]] = set()

MAX_LINES = 400  # issue 15.4: no module over 400 lines
# Modules allowed over MAX_LINES (none since issue 15.4). Each must be over it: one that fits
# is struck off, so the list only shrinks.
LARGE_TODAY: frozenset[str] = frozenset()


def room_of(path: Path) -> str:
    rel = path.relative_to(ROOT)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def imports() -> dict[str, dict[str, set[str]]]:
    """room -> imported room -> the modules (relative paths) that import it."""
    graph: dict[str, dict[str, set[str]]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        room = room_of(path)
        graph.setdefault(room, {})
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                parts = name.split(".")
                if parts[0] == "softplc" and len(parts) > 1 and parts[1] != room:
                    rel = str(path.relative_to(ROOT))
                    graph[room].setdefault(parts[1], set()).add(rel)
    return graph


def cycles(graph: dict[str, dict[str, set[str]]]) -> set[frozenset[str]]:
    """The strongly connected groups of more than one room (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: set[frozenset[str]] = set()

    def visit(room: str) -> None:
        index[room] = low[room] = len(index)
        stack.append(room)
        for other in graph.get(room, {}):
            if other not in index:
                visit(other)
                low[room] = min(low[room], low[other])
            elif other in stack:
                low[room] = min(low[room], index[other])
        if low[room] == index[room]:
            group = set()
            while True:
                member = stack.pop()
                group.add(member)
                if member == room:
                    break
            if len(group) > 1:
                found.add(frozenset(group))

    for room in sorted(graph):
        if room not in index:
            visit(room)
    return found


def test_every_room_is_known() -> None:
    unknown = sorted(set(imports()) - set(ALLOWED) - {"__init__", "__main__"})
    assert not unknown, f"rooms without an import allowlist in this test: {unknown}"


def test_rooms_import_only_what_their_allowlist_names() -> None:
    wrong = [f"{room} imports {other} ({', '.join(sorted(where))})"
             for room, deps in sorted(imports().items())
             for other, where in sorted(deps.items())
             if other not in ALLOWED.get(room, frozenset())]
    assert not wrong, "imports outside the allowlist:\n" + "\n".join(wrong)


def test_the_core_imports_no_other_room() -> None:
    assert not imports()["core"]


def test_only_the_cli_imports_the_debug_room() -> None:
    users = sorted(room for room, deps in imports().items() if "debug" in deps)
    assert users == ["cli"], f"rooms importing softplc.debug: {users}"


def test_no_room_imports_another_rooms_private_names() -> None:
    """A room meets another through its public names (issue 40.5: the debugger used
    api.clicmds' private _call): `from softplc.x.m import _name` across rooms fails."""
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        room = room_of(path)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                    and node.module.startswith("softplc.") \
                    and node.module.split(".")[1] != room:
                found += [f"{path.relative_to(ROOT)}: {node.module}.{alias.name}"
                          for alias in node.names if alias.name.startswith("_")]
    assert not found, "private names imported across rooms:\n" + "\n".join(found)


# The sub-rooms of the runtime (issue 40.5) and what each may import of the runtime. "scan" is
# runtime/*.py, what runs in the scan process; "scan.clock" names one of its modules. clock and
# realtime import nothing of softplc, so the lower sub-rooms may use them. Within a sub-room
# anything goes; a new edge between sub-rooms fails until it is argued here.
SUBROOMS: dict[str, frozenset[str]] = {
    "shared": frozenset({"scan.clock"}),  # the channel's timeouts
    "retain": frozenset({"scan.clock", "scan.realtime"}),  # the writer's thread
    "scan": frozenset({"shared", "retain"}),
    "serve": frozenset({"shared"}),
    "offline": frozenset({"scan"}),
    "supervise": frozenset({"scan", "shared", "serve", "retain"}),
}
# Rooms outside the runtime that may import only some of its sub-rooms.
RUNTIME_USERS: dict[str, frozenset[str]] = {
    "sparkplug": frozenset({"shared"}),  # a service over the snapshot, started by config
    "debug": frozenset({"scan", "offline"}),  # traces and simulate, never a live process
}


def subroom_of(parts: tuple[str, ...] | list[str]) -> str:
    """The sub-room of softplc.runtime.<parts...> (module path parts after 'runtime')."""
    return parts[0] if parts[0] in SUBROOMS and len(parts) > 1 else f"scan.{parts[0]}"


def runtime_imports() -> list[tuple[str, str, str]]:
    """(importing room or runtime sub-room, imported sub-room target, importing file)."""
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] == "runtime":
            inner = rel.parts[1:]
            here = inner[0] if len(inner) > 1 else "scan"
        else:
            here = room_of(path)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] if node.module != "softplc.runtime" else \
                    [f"softplc.runtime.{alias.name}" for alias in node.names]
            else:
                continue
            for name in names:
                parts = name.split(".")
                if parts[:2] == ["softplc", "runtime"] and len(parts) > 2:
                    found.append((here, subroom_of(parts[2:]), str(rel)))
    return found


def test_runtime_subrooms_import_only_what_their_walls_name() -> None:
    wrong = []
    for here, target, where in runtime_imports():
        allowed = SUBROOMS.get(here) if here in SUBROOMS else RUNTIME_USERS.get(here)
        if allowed is None or target.split(".")[0] == here:
            continue
        if target not in allowed and not (target.startswith("scan.") and "scan" in allowed):
            wrong.append(f"{where} ({here}) imports runtime {target}")
    assert not wrong, "imports through the runtime's walls:\n" + "\n".join(sorted(set(wrong)))


def test_the_runtime_walls_see_every_subroom() -> None:
    on_disk = {p.parent.name for p in (ROOT / "runtime").glob("*/__init__.py")}
    assert on_disk == set(SUBROOMS) - {"scan"}
    seen = {(here, target) for here, target, _ in runtime_imports()}
    assert ("supervise", "scan.scanproc") in seen  # the walk sees the supervisor start a scan


def test_no_cycles_between_rooms_but_the_known_ones() -> None:
    assert cycles(imports()) == KNOWN_CYCLES


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b": {"a.py"}}, "b": {"c": {"b.py"}}, "c": {"a": {"c.py"}}, "d": {}}
    assert cycles(graph) == {frozenset({"a", "b", "c"})}
    assert cycles({"a": {"b": {"a.py"}}, "b": {}}) == set()


def modules() -> dict[str, Path]:
    """Dotted module name -> its file (a package by its own name)."""
    found = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(("softplc", *parts))
        found[name.removesuffix(".__init__")] = path
    return found


def module_imports() -> dict[str, dict[str, set[str]]]:
    """module -> the softplc modules it imports, anywhere in it, TYPE_CHECKING included
    (`from softplc.x import y` counts as an import of softplc.x.y when that is a module).
    Empty packages (their __init__) are left out: importing a submodule runs them, but they
    import nothing back."""
    mods = modules()
    graph: dict[str, dict[str, set[str]]] = {}
    for name, path in mods.items():
        deps = graph.setdefault(name, {})
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            else:
                continue
            for target in targets:
                if target in mods and target != name and mods[target].name != "__init__.py":
                    deps.setdefault(target, set()).add(name)
    return graph


def test_no_import_circle_between_modules_but_the_known_ones() -> None:
    found = cycles(module_imports())
    assert found == KNOWN_MODULE_CYCLES, "import circles between modules:\n" + "\n".join(
        " <-> ".join(sorted(group)) for group in found ^ KNOWN_MODULE_CYCLES)


def test_the_module_graph_sees_type_only_imports() -> None:
    graph = module_imports()
    # runtime/supervise/supervisor.py and others import under TYPE_CHECKING too; one known edge:
    typed = [name for name, path in modules().items()
             if "if TYPE_CHECKING:" in path.read_text(encoding="utf-8")]
    assert typed and all(graph[name] for name in typed)


def module_lines() -> dict[str, int]:
    """Relative path under softplc/ -> its number of lines."""
    return {str(path.relative_to(ROOT)): len(path.read_text(encoding="utf-8").splitlines())
            for path in sorted(ROOT.rglob("*.py"))}


def test_no_module_is_over_the_size_limit() -> None:
    sizes = module_lines()
    over = [f"{name}: {n} lines" for name, n in sizes.items()
            if n > MAX_LINES and name not in LARGE_TODAY]
    assert not over, f"modules over {MAX_LINES} lines (split them along their concerns):\n" \
        + "\n".join(over)


def test_the_large_modules_still_listed_are_large() -> None:
    sizes = module_lines()
    fits = sorted(name for name in LARGE_TODAY if sizes.get(name, 0) <= MAX_LINES)
    assert not fits, f"strike these off LARGE_TODAY (gone or at most {MAX_LINES} lines): {fits}"
