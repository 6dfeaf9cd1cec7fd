"""One Debug Adapter Protocol session (docs/debug.md, DAP): an editor attached to a running
PLC through its HTTP API, shown as one thread, "scan", stopped where a breakpoint hit.

Owns: the requests and their responses, the events, the breakpoints this session set (a line
of the program's YAML -> the transitions of its block -> PLC breakpoints, removed again at
the end), the poll of status (every 100 ms) that turns a pause into a `stopped` event.
Does not know: how a pause, a step or `why` works (the PLC does; api/client.py asks it),
the framing and the servers (debug/dapwire.py, debug/dapserve.py).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.core.errors import SoftplcError
from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.debug.dapbreaks import VERB, BreakBook
from softplc.debug.dapsource import Block, LineMap
from softplc.debug.dapvars import Var, marking_vars, symbol_var, symbol_vars, why_vars
from softplc.program.compiler import compile_file

Send = Callable[[dict[str, Any]], None]
POLL_S: Final = 0.1
THREAD: Final = 1
MARKING, SYMBOLS, WHY = 1, 2, 3
FIRST_HANDLE: Final = 100

CAPABILITIES: Final[dict[str, Any]] = {
    "supportsConfigurationDoneRequest": True,
    "supportsFunctionBreakpoints": True,  # fire:T, enabled:T, when:EXPR (or just T)
    "supportsConditionalBreakpoints": False,
    "supportsHitConditionalBreakpoints": False,
    "supportsEvaluateForHovers": True,
    "supportsStepBack": False,
    "supportsSetVariable": False,
    "supportsRestartRequest": False,
    "supportsTerminateRequest": False,
    "supportTerminateDebuggee": False,
    "supportsSteppingGranularity": False,
    "exceptionBreakpointFilters": [],
    "breakpointModes": [
        {"mode": "fire", "label": "Fires", "appliesTo": ["source"],
         "description": "pause at the end of the scan in which the transition fires"},
        {"mode": "enabled", "label": "Becomes enabled", "appliesTo": ["source"],
         "description": "pause at the end of the scan in which it becomes enabled"}],
}
# DAP has no capability for `pause`: the request is answered unsuccessfully, saying why.
NO_PAUSE: Final = ("pause is not supported: the PLC pauses only where a breakpoint hits (a "
                   "transition's line, or a function breakpoint when:EXPR)")


class Refused(SoftplcError):
    """A request answered with success: false and this message."""


class DapSession:
    """Requests in through `handle`; responses and events out through `send` (from this
    thread and from the poller's)."""

    def __init__(self, client: ApiClient, send: Send) -> None:
        self.client = client
        self._send = send
        self._seq = 0
        self._lock = threading.Lock()
        self.ended = False
        self.book = BreakBook(client)
        self._places: tuple[str, ...] = ()
        self._pause: dict[str, Any] | None = None
        self._pause_key: tuple[Any, ...] | None = None
        self._handles: dict[int, tuple[Var, ...]] = {}
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self._later: list[tuple[str, dict[str, Any]]] = []

    # -- messages ---------------------------------------------------------------------------

    def handle(self, message: dict[str, Any]) -> None:
        if message.get("type") != "request":
            return
        command = str(message.get("command"))
        handler = _REQUESTS.get(command)
        args = message.get("arguments") or {}
        try:
            if handler is None:
                raise Refused(f"{command} is not supported by softplc dap")
            body, error = handler(self, args), None
        except Refused as exc:
            body, error = None, str(exc)
        except ApiError as exc:
            body, error = None, f"the PLC refused (HTTP {exc.status}): {exc.message}"
        except ApiUnreachable as exc:
            body, error = None, str(exc)
        except (ValueError, TypeError, AttributeError) as exc:  # arguments of the wrong shape
            body, error = None, f"{command}: bad arguments ({exc})"
        reply = {"type": "response", "request_seq": message.get("seq"), "command": command,
                 "success": error is None, **({"body": body} if body is not None else {})}
        self._write({**reply, "message": error} if error else reply)
        later, self._later = self._later, []
        for event, event_body in later:
            self.event(event, event_body)

    def event(self, name: str, body: dict[str, Any]) -> None:
        self._write({"type": "event", "event": name, "body": body})

    def output(self, text: str) -> None:
        self.event("output", {"category": "console", "output": text + "\n"})

    def _write(self, message: dict[str, Any]) -> None:
        with self._lock:
            self._seq += 1
            try:
                self._send({"seq": self._seq, **message})
            except OSError:  # the editor is gone: the session ends with the stream
                self._stop.set()

    # -- the session's life -----------------------------------------------------------------

    def initialize(self, args: dict[str, Any]) -> dict[str, Any]:
        self.book.base = 1 if args.get("linesStartAt1", True) else 0
        return dict(CAPABILITIES)

    def attach(self, args: dict[str, Any]) -> dict[str, Any]:
        status = self.client.status()  # unreachable or refused: the attach fails
        program = args.get("program")
        if program:
            net = _compile(str(program))
            self.book.lines, self._places = LineMap.of(net, net.source), net.place_names
            self.book.program = net.name
            if status.get("program") != net.name:
                self.output(f"softplc dap: {program} is program {net.name}, the PLC runs "
                            f"{status.get('program')}: lines may not match")
        self.output(f"softplc dap: attached to {self.client.url}: program "
                    f"{status.get('program')}, {status.get('state')}, scan count "
                    f"{status.get('scan_count')}")
        self._later.append(("initialized", {}))
        return {}

    def configuration_done(self, args: dict[str, Any]) -> dict[str, Any]:
        if self._poller is None:
            self._poller = threading.Thread(target=self._poll, name="dap-poll", daemon=True)
            self._poller.start()
        return {}

    def disconnect(self, args: dict[str, Any]) -> dict[str, Any]:
        self.close()
        return {}

    def close(self) -> None:
        """Remove this session's breakpoints and let a paused PLC run on (at a disconnect,
        or when the editor went away without one)."""
        if self.ended:
            return
        self.ended = True
        self._stop.set()
        if self._poller is not None and self._poller is not threading.current_thread():
            self._poller.join(5.0)
        self.book.clear()
        # Asked, not looked up first: status lags the scan by up to 50 ms.
        with contextlib.suppress(ApiError, ApiUnreachable):  # not paused (409), no PLC
            self.client.continue_()

    # -- breakpoints ------------------------------------------------------------------------

    def set_breakpoints(self, args: dict[str, Any]) -> dict[str, Any]:
        source = dict(args.get("source") or {})
        wanted = args.get("breakpoints")
        if wanted is None:
            wanted = [{"line": line} for line in args.get("lines") or []]
        answers = self.book.set_source(str(source.get("path") or ""), wanted)
        return {"breakpoints": [{**answer, "source": source} for answer in answers]}

    def set_function_breakpoints(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"breakpoints": self.book.set_functions(args.get("breakpoints") or [])}

    # -- running and stopping ---------------------------------------------------------------

    def _poll(self) -> None:
        while not self._stop.is_set():
            with contextlib.suppress(ApiError, ApiUnreachable):  # asked again in 100 ms
                self.observe(self.client.status())
            self._stop.wait(POLL_S)

    def observe(self, status: dict[str, Any]) -> None:
        """A new pause is a `stopped` event; its end seen (a `continue` from elsewhere too),
        a `continued` one."""
        paused = status.get("paused")
        if paused:
            key = (paused.get("k"), paused.get("reason"))
            if key != self._pause_key:
                self._pause, self._pause_key, self._handles = paused, key, {}
                self.event("stopped", self._stopped(paused))
        elif self._pause is not None:
            self._pause = None
            self.event("continued", {"threadId": THREAD, "allThreadsContinued": True})

    def _stopped(self, paused: dict[str, Any]) -> dict[str, Any]:
        plc_ids = [b.get("id") for b in paused.get("breakpoints") or []]
        return {"reason": "step" if paused.get("steps") else "breakpoint",
                "description": f"paused after scan {paused.get('k')} (scan count "
                               f"{paused.get('scan_count')})",
                "text": str(paused.get("reason", "")), "threadId": THREAD,
                "allThreadsStopped": True,
                "hitBreakpointIds": self.book.dap_ids(plc_ids)}

    def continue_(self, args: dict[str, Any]) -> dict[str, Any]:
        self.client.continue_()
        return {"allThreadsContinued": True}

    def next(self, args: dict[str, Any]) -> dict[str, Any]:
        self.client.step(1)
        return {}

    def pause(self, args: dict[str, Any]) -> dict[str, Any]:
        raise Refused(NO_PAUSE)

    # -- what a stop shows ------------------------------------------------------------------

    def threads(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"threads": [{"id": THREAD, "name": "scan"}]}

    def stack_trace(self, args: dict[str, Any]) -> dict[str, Any]:
        paused = self._pause or {}
        k, hit = paused.get("k"), self._hit()
        if hit is not None:
            name, on, block = hit
            frame = {"name": f"{name} {VERB[on]} (scan {k})",
                     "source": _source(block.path), "line": block.first - 1 + self.book.base}
        elif self.book.lines is not None:
            frame = {"name": f"{self.book.program} after scan {k}",
                     "source": _source(self.book.lines.program), "line": self.book.base}
        else:
            frame = {"name": f"program after scan {k}", "line": 0}
        return {"stackFrames": [{"id": 1, "column": self.book.base, **frame}], "totalFrames": 1}

    def _hit(self) -> tuple[str, str, Block] | None:
        """The transition whose breakpoint the pause names first: its name, the kind of
        breakpoint (fire or enabled) and its block."""
        for point in (self._pause or {}).get("breakpoints") or []:
            name, on = str(point.get("target")), str(point.get("on"))
            block = self.book.lines.where(name) if self.book.lines else None
            if on in ("fire", "enabled") and block is not None:
                return name, on, block
        return None

    def scopes(self, args: dict[str, Any]) -> dict[str, Any]:
        scopes = [_scope("Marking", MARKING), _scope("Symbols", SYMBOLS)]
        hit = self._hit()
        if hit is not None:
            scopes.append(_scope(f"Why {hit[0]}", WHY))
        return {"scopes": scopes}

    def variables(self, args: dict[str, Any]) -> dict[str, Any]:
        ref = int(args.get("variablesReference", 0))
        if ref == MARKING:
            found = marking_vars(self.client.status(), self._places)
        elif ref == SYMBOLS:
            forced = self.client.status().get("forced") or {}
            found = symbol_vars(self.client.symbols(), forced)
        elif ref == WHY and (hit := self._hit()) is not None:
            found = why_vars(self.client.why(hit[0]))
        else:
            found = list(self._handles.get(ref, ()))
        return {"variables": [self._variable(var) for var in found]}

    def _variable(self, var: Var) -> dict[str, Any]:
        ref = 0
        if var.children:
            ref = FIRST_HANDLE + len(self._handles)
            self._handles[ref] = var.children
        return {"name": var.name, "value": var.value, "type": var.type,
                "variablesReference": ref}

    def evaluate(self, args: dict[str, Any]) -> dict[str, Any]:
        """A symbol's typed value (a hover, the watch list), as the Symbols scope shows it."""
        name = str(args.get("expression", "")).strip()
        try:
            var = symbol_var(name, self.client.symbol(name),
                             name in (self.client.status().get("forced") or {}))
        except ApiError as exc:
            raise Refused(f"{name}: {exc.message}") from None
        reply = self._variable(var)
        return {"result": reply["value"], "type": reply["type"],
                "variablesReference": reply["variablesReference"]}

    def nothing(self, args: dict[str, Any]) -> dict[str, Any]:
        return {}


_REQUESTS: Final[dict[str, Callable[[DapSession, dict[str, Any]], dict[str, Any]]]] = {
    "initialize": DapSession.initialize,
    "attach": DapSession.attach,
    "launch": DapSession.attach,  # a PLC is never launched here: both attach to it
    "configurationDone": DapSession.configuration_done,
    "setBreakpoints": DapSession.set_breakpoints,
    "setFunctionBreakpoints": DapSession.set_function_breakpoints,
    "setExceptionBreakpoints": DapSession.nothing,
    "threads": DapSession.threads,
    "stackTrace": DapSession.stack_trace,
    "scopes": DapSession.scopes,
    "variables": DapSession.variables,
    "evaluate": DapSession.evaluate,
    "continue": DapSession.continue_,
    "next": DapSession.next,
    "pause": DapSession.pause,
    "disconnect": DapSession.disconnect,
}


def _compile(program: str) -> CompiledNet:
    path = Path(program).expanduser().resolve()
    try:
        return compile_file(str(path))
    except ProgramError as exc:
        shown = "; ".join(str(p) for p in exc.problems[:3])
        raise Refused(f"{program}: {len(exc.problems)} problem(s): {shown}") from None
    except OSError as exc:
        raise Refused(f"cannot read {program}: {exc.strerror}") from None


def _source(path: str) -> dict[str, Any]:
    return {"name": os.path.basename(path), "path": path}


def _scope(name: str, ref: int) -> dict[str, Any]:
    return {"name": name, "variablesReference": ref, "expensive": False}
