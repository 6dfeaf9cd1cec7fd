"""Every command of `softplc`: its name, the module that defines its parser and handler, the
function there that adds its arguments, and its one-line help.

Owns: the list `softplc --help` shows, in its order, without importing any command's module
(a client command's start-up must not pay for numpy, the compiler or the servers: issue 40).
Does not know: any command's arguments.
"""

from __future__ import annotations

from softplc.core.lifecycle import Command, accepting

TYPE_CHECKING = False  # typing costs every start (`softplc --help`); mypy reads it
if TYPE_CHECKING:
    from typing import Final


class Entry:
    """`module.add(parser)` adds the command's arguments and sets `func`, its handler.
    A plain class: `dataclasses` costs `inspect`, `ast` and `dis` at every start."""

    __slots__ = ("add", "help", "module", "program")

    def __init__(self, module: str, add: str, help: str, program: str = "") -> None:
        self.module, self.add, self.help = module, add, help
        self.program = program  # where its program goes (args.<program>): it takes --pou


def _lifecycle(command: str, what: str) -> Entry:
    return Entry(_CLIENT, "add_lifecycle", f"{what} (accepted in {accepting(Command(command))})")


_LOCAL: Final = "softplc.cli.local"
_CLIENT: Final = "softplc.api.clicmds"
_DEBUG: Final = "softplc.debug.debugcli"
_BREAK: Final = "softplc.debug.breakcli"

COMMANDS: Final[dict[str, Entry]] = {
    "check": Entry(_LOCAL, "add_check", "validate and compile a program (or check a symbols "
                   "file), its drivers' plants and channels; opens nothing", "program"),
    "run": Entry("softplc.cli.runargs", "add_run",
                 "run a soft PLC (scan process + Modbus/HTTP process)", "program"),
    "simulate": Entry(_LOCAL, "add_simulate",
                      "run a program on a simulated plant in virtual time", "program"),
    "replay": Entry(_LOCAL, "add_replay",
                    "re-run a trace's inputs and compare outputs bit for bit", "program"),
    "bench": Entry(_LOCAL, "add_bench", "benchmarks of the engine, scan timing and Modbus"),
    "analyze": Entry("softplc.analysis.cli", "add_analyze", "state-space and structural "
                     "analysis of a program (YAML) or a PNML net", "net"),
    "import": Entry("softplc.sfc.importcmd", "add_import", "write a PLCopen XML SFC chart "
                    "as a softplc program and symbols file (docs/sfc.md)", "chart"),
    "export": Entry("softplc.analysis.cli", "add_export",
                    "write a program as PNML (ISO/IEC 15909-2)", "program"),
    "why": Entry(_DEBUG, "add_why", "why a transition fires or not: the places short of "
                 "tokens, the guard with the values it read, a delay, a conflict, forces; on a "
                 "running softplc, or at a scan of a trace; without a transition, why "
                 "nothing moves (docs/debug.md)", "program"),
    "vcd": Entry(_DEBUG, "add_vcd", "export a trace as a VCD file (IEEE 1364 value change "
                 "dump) for GTKWave and other waveform viewers: every symbol and every place's "
                 "marking, scan by scan", "program"),
    "break": Entry(_BREAK, "add_break", "breakpoints: pause the running PLC at the end of the "
                   "scan in which a transition fires or becomes enabled, or a condition becomes "
                   "true (docs/debug.md)"),
    "step": Entry(_BREAK, "add_step",
                  "while paused: run exactly N scans, then pause again (scan count + N)"),
    "continue": Entry(_BREAK, "add_continue", "while paused: run on until a breakpoint hits"),
    "dap": Entry("softplc.debug.dapserve", "add_dap", "a Debug Adapter Protocol adapter for "
                 "editors (VS Code): breakpoints on the lines of the program's YAML, step a "
                 "scan, continue, the marking, symbols and why of the running PLC at --api "
                 "(docs/debug.md)"),
    "download": Entry(_CLIENT, "add_download", "download a program to a running softplc: the "
                      "program, its io image and subnets in one bundle (docs/programs.md, "
                      "program bundles)", "program"),
    "upload": Entry(_CLIENT, "add_upload",
                    "get the running program back as files, byte for byte as downloaded"),
    "start": _lifecycle("start", "start a downloaded or reset program from its initial "
                        "marking (after a stop: resume, or reset then start)"),
    "stop": _lifecycle("stop", "stop the program: outputs safe, marking frozen"),
    "resume": _lifecycle("resume",
                         "resume a program stopped while running, with its marking (warm)"),
    "reset": _lifecycle("reset", "back to the initial marking, stopped"),
    "kill": _lifecycle("kill", "stop at once without committing the scan's outputs"),
    "force": Entry(_CLIENT, "add_force", "force a symbol (input or output) to a value"),
    "unforce": Entry(_CLIENT, "add_unforce", "release a forced symbol (all without one)"),
    "status": Entry(_CLIENT, "add_status", "state, program, scans, timing, marking"),
    "users": Entry("softplc.api.admincmds", "add_users", "named users with roles (viewer, "
                   "operator, engineer, admin) and their API keys, in STATE_DIR/users"),
    "audit": Entry("softplc.api.admincmds", "add_audit",
                   "show the audit trail of STATE_DIR, or check its hash chain (--verify)"),
    "keys": Entry("softplc.api.signcmds", "add_keys",
                  "an engineer's Ed25519 keys for signing programs, and a PLC's trusted keys"),
    "sign": Entry("softplc.api.signcmds", "add_sign", "sign a program (the bundle softplc "
                  "download sends) or a bundle zip with an engineer's key: FILE.sig", "program"),
    "trust": Entry("softplc.api.trustcmds", "add_trust", "client certificates the OPC UA "
                   "server (STATE_DIR/pki) or, with --modbus, the Modbus/TCP Security port "
                   "trusts: a refused one waits in rejected/ until accepted"),
}
