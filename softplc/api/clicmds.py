"""The client commands of the CLI: `softplc download|start|stop|resume|reset|kill|status`.

Owns: their arguments (every one takes --api URL, --token, --state-dir, --timeout), exit
codes (0 done, 1 refused or bad program with every problem on stderr, 2 no API answering)
and what a person reads. Does not know: HTTP (client.py does), the PLC.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from softplc.api.client import (
    DEFAULT_URL,
    URL_ENV,
    ApiClient,
    ApiError,
    ApiUnreachable,
    default_url,
)
from softplc.core.lifecycle import Command
from softplc.security.auth import TOKEN_ENV

TYPE_CHECKING = False  # typing costs every client command's start (issue 40); mypy reads it
if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import Any, Final

EXIT_OK: Final = 0
EXIT_REFUSED: Final = 1
EXIT_UNREACHABLE: Final = 2
_SCAN_WORDS = frozenset(c.value for c in Command)  # the scan's names of commands (_own_words)


def add_download(download: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    download.add_argument("program", help="program file (YAML); the files it references go "
                          "along; or a bundle (.zip) sent as it is")
    download.add_argument("--online", action="store_true",
                          help="online change while RUNNING: keep the marking by place name; "
                          "new places start with their declared tokens; refused when tokens "
                          "would be lost or a timed firing is in progress (default: off)")
    download.add_argument("--replace", action="store_true",
                          help="with --online: a program with another name on the same devices "
                          "replaces the running one from its initial marking (refused without; "
                          "default: off)")
    download.add_argument("--dry-run", action="store_true",
                          help="show what the download would do against the running state "
                          "(kept, new and dropped places with tokens, outputs changing hands, "
                          "accepted or not) and apply nothing (default: off)")
    from softplc.api.signcmds import add_download_options
    add_download_options(download)  # --sign-key, --version, --signature, --allow-older
    connection_options(download)
    download.set_defaults(func=cmd_download)


def add_upload(upload: argparse.ArgumentParser) -> None:
    upload.add_argument("-o", "--output", metavar="DIR", default=".",
                        help="write the files under DIR at their bundle paths, overwriting "
                        "(default: the current directory)")
    connection_options(upload)
    upload.set_defaults(func=cmd_upload)


def add_lifecycle(parser: argparse.ArgumentParser) -> None:
    """start, stop, resume, reset, kill: the command is the parser's name (args.command)."""
    connection_options(parser)
    parser.set_defaults(func=cmd_lifecycle)


def add_force(force: argparse.ArgumentParser) -> None:
    force.add_argument("symbol", help="an input, output or memory symbol of the program")
    force.add_argument("value", help="as the symbol's type takes it: 0/1 or true/false, an "
                       "integer (-3), a decimal (12.5)")
    connection_options(force)
    force.set_defaults(func=cmd_force)


def add_unforce(unforce: argparse.ArgumentParser) -> None:
    unforce.add_argument("symbol", nargs="?", default=None,
                         help="the forced symbol to release (default: every forced symbol)")
    connection_options(unforce)
    unforce.set_defaults(func=cmd_unforce)


def add_status(status: argparse.ArgumentParser) -> None:
    status.add_argument("--json", action="store_true",
                        help="print the status as JSON (default: off, a summary)")
    connection_options(status)
    status.set_defaults(func=cmd_status)


def connection_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--api", metavar="URL", default=default_url(),
                        help=f"the softplc's HTTP API (default: ${URL_ENV}, else "
                        f"{DEFAULT_URL})")
    parser.add_argument("--token", default=None,
                        help=f"an API key (softplc users key NAME) (default: ${TOKEN_ENV}, "
                        "else --state-dir's api_token, else that of this account's server at "
                        "a loopback --api)")
    parser.add_argument("--user", metavar="NAME", default=None,
                        help="log in as NAME; the password is read from the terminal (or one "
                        "line of stdin) (default: the key as for --token)")
    parser.add_argument("--state-dir", metavar="DIR", default=None,
                        help="the server's state directory, to read the owner's key "
                        "DIR/api_token from (default: found for a loopback --api)")
    parser.add_argument("--timeout", metavar="SECONDS", type=float, default=10.0,
                        help="how long to wait for an answer (default: %(default)s)")
    parser.add_argument("--ca", metavar="FILE", default=None,
                        help="verify an https --api against this CA file; the PLC's own "
                        "certificate pins it (default: $SOFTPLC_API_CA, else --state-dir's "
                        "certificate, else the system's CAs)")


def call(args: argparse.Namespace, what: str,
          action: Callable[[ApiClient], dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    """Run `action`, turning failures into a message on stderr and an exit code."""
    try:
        password = _password() if args.user else None
        client = ApiClient(args.api, args.token, args.timeout, state_dir=args.state_dir,
                           user=args.user, password=password, ca=args.ca)
        return EXIT_OK, action(client)
    except ApiError as exc:
        message = _own_words(exc.message, " refused")  # said once is enough
        print(f"softplc {what}: refused (HTTP {exc.status}): {message}", file=sys.stderr)
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        if exc.problems:
            print(f"{len(exc.problems)} problem(s)", file=sys.stderr)
        return EXIT_REFUSED, {}
    except ApiUnreachable as exc:
        print(f"softplc {what}: {exc}", file=sys.stderr)
        return EXIT_UNREACHABLE, {}
    except ValueError as exc:  # a malformed --api URL
        print(f"softplc {what}: {exc}", file=sys.stderr)
        return EXIT_UNREACHABLE, {}


def _password() -> str:
    from softplc.api.admincmds import read_password  # users, audit: not every command's cost
    return read_password(confirm=False)


def cmd_download(args: argparse.Namespace) -> int:
    from softplc.api.signcmds import download_body
    from softplc.api.signcmds import signature_for as signature_of
    from softplc.program import bundle as bundles

    try:
        blob, _, absent = download_body(args.program)  # a program's bundle, or a bundle zip
        signature = signature_of(args, blob)  # --sign-key [--version], --signature
    except (OSError, UnicodeDecodeError, ValueError, bundles.BundleError) as exc:
        print(f"softplc download: cannot read {args.program}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    if absent:  # compatibility: the server resolves them against its programs directory
        print(f"softplc download: not found here: {', '.join(map(str, absent))}; sending the "
              "program as plain text (the server looks for them in its programs directory)",
              file=sys.stderr)
        name = Path(args.program).name
        code, reply = call(args, "download", lambda client: client.download_text(
            blob.decode(), args.online, name, args.replace, args.dry_run, signature,
            args.allow_older))
    else:
        code, reply = call(args, "download", lambda client: client.download_bundle(
            blob, args.online, args.replace, args.dry_run, signature, args.allow_older))
    if code != EXIT_OK:
        return code
    if "plan" in reply:
        print(format_plan(reply["plan"]))
        return EXIT_OK if reply["plan"].get("accepted") else EXIT_REFUSED
    print(said("download", reply))
    return code


def format_plan(plan: dict[str, Any]) -> str:
    """A dry run's plan as a person reads it."""
    records = plan.get("records") or {}
    lines = [f"dry run: {plan.get('from') or '(nothing running)'} -> {plan.get('to')} "
             f"(state {plan.get('state')}); nothing applied"]
    for title, key in (("kept places (tokens carried over)", "kept"),
                       ("new places (start with their declared tokens)", "new"),
                       ("dropped places (must be empty)", "dropped")):
        places = plan.get(key) or {}
        lines.append(f"{title}:" + ("" if places else " none"))
        for place, tokens in sorted(places.items()):
            shown = f"  {place:<24} {tokens}"
            if records.get(place):
                shown += "  " + ", ".join(json.dumps(r, sort_keys=True) for r in records[place])
            lines.append(shown)
    outputs = plan.get("outputs") or {}
    lines.append("outputs no longer driven: " + (", ".join(outputs.get("released") or [])
                                                 or "none"))
    lines.append("outputs newly driven:     " + (", ".join(outputs.get("taken") or []) or "none"))
    lines.append(("would be ACCEPTED: " if plan.get("accepted") else "would be REFUSED: ")
                 + str(plan.get("verdict")))
    return "\n".join(lines)


def cmd_upload(args: argparse.Namespace) -> int:
    from softplc.program import bundle as bundles

    code, blob = _call_bytes(args, "upload", lambda client: client.upload())
    if code != EXIT_OK:
        return code
    try:
        bundle = bundles.unpack(blob, "the uploaded bundle")
        written = bundles.write_out(bundle, args.output)
    except (bundles.BundleError, OSError) as exc:
        print(f"softplc upload: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    for path in written:
        print(path)
    print(f"program {Path(args.output) / bundle.program} ({len(written)} file(s))")
    return EXIT_OK


def _call_bytes(args: argparse.Namespace, what: str,
                action: Callable[[ApiClient], bytes]) -> tuple[int, bytes]:
    got: list[bytes] = []

    def run(client: ApiClient) -> dict[str, Any]:
        got.append(action(client))
        return {}

    code, _ = call(args, what, run)
    return code, got[0] if got else b""


def said(command: str, reply: dict[str, Any]) -> str:
    """A command's reply as one line that names the command and the state once each: the
    scan's messages already start with the command ("stop: now STOPPED") and may name the
    state, so nothing is added that is already there."""
    message = _own_words(str(reply.get("message") or "done"), "")
    if not message.startswith(command):
        message = f"{command}: {message}"
    state = reply.get("state")
    if state and str(state) not in message:
        message += f" (state {state})"
    return message


def _own_words(message: str, after: str) -> str:
    """`message` without the scan's name of the command ("unbreak: removed b1", "stop refused:
    ..."): the client names it as the person typed it (`break clear`), once (the one place)."""
    head, sep, rest = message.partition(f"{after}: ")
    return rest if sep and head in _SCAN_WORDS else message


def cmd_lifecycle(args: argparse.Namespace) -> int:
    command: str = args.command
    code, reply = call(args, command, lambda client: client.command(command))
    if code == EXIT_OK:
        print(said(command, reply))
    return code


def _force_value(text: str) -> bool | int | float | None:
    """The value as a number, whatever the symbol's type: true/false (on/off), an integer
    (`-3`, `0x10`) or a decimal (`12.5`, `1e3`). The server checks it against the symbol's
    type (core/present.py), so the CLI needs no second look-up and no type of its own."""
    lowered = text.strip().lower()
    if lowered in ("true", "on", "false", "off"):
        return lowered in ("true", "on")
    try:
        return int(lowered, 0)
    except ValueError:
        pass
    try:
        return float(lowered)  # nan and inf parse too: the server names why it refuses them
    except ValueError:
        return None


def cmd_force(args: argparse.Namespace) -> int:
    value = _force_value(args.value)
    if value is None:
        print(f"softplc force: value {args.value!r} is not true/false or a number",
              file=sys.stderr)
        return EXIT_REFUSED
    code, reply = call(args, "force", lambda client: client.force(args.symbol, value))
    if code == EXIT_OK:
        print(said("force", reply))
    return code


def cmd_unforce(args: argparse.Namespace) -> int:
    code, reply = call(args, "unforce", lambda client: client.unforce(args.symbol))
    if code == EXIT_OK:
        print(said("unforce", reply))
    return code


def cmd_status(args: argparse.Namespace) -> int:
    code, status = call(args, "status", lambda client: client.status())
    if code == EXIT_OK:
        print(json.dumps(status, indent=2, sort_keys=True) if args.json else format_status(status))
    return code


def format_status(status: dict[str, Any]) -> str:
    """A readable summary of GET /api/v1/status."""
    timing = status.get("timing") or {}
    program = status.get("program") or "(none)"
    digest = status.get("program_hash") or ""
    fault = (f" (fault code {status['fault_code']}, {status.get('fault_name') or '?'})"
             if status.get("fault_code") else "")
    paused = status.get("paused")
    pause = (f" PAUSED after scan {paused.get('k')} ({paused.get('reason')}; outputs "
             f"{paused.get('outputs')}; softplc step / continue)"
             if isinstance(paused, dict) else "")
    lines = [
        f"state       {status.get('state', '?')}{fault}{pause}",
        *([f"fault       {status['fault_reason']}"] if fault and status.get("fault_reason")
          else []),
        f"program     {program}" + (f"  hash {digest[:12]}" if digest else ""),
        f"start mode  {status.get('start_mode', '?')}"
        + (f" ({status['start_reason']})" if status.get("start_reason") else ""),
        f"boot policy {status.get('boot_policy', '?')}"
        + (f" ({status['boot_policy_source']})" if status.get("boot_policy_source") else ""),
        f"scans       {status.get('scan_count', 0)}, period {_us(status.get('period_us'))}",
        f"execution   median {_us(timing.get('exec_median_us'))}, "
        f"p99 {_us(timing.get('exec_p99_us'))}, max {_us(timing.get('exec_max_us'))}",
        f"lateness    p99 {_us(timing.get('p99_lateness_us'))}, "
        f"max {_us(timing.get('lateness_max_us'))}; overruns {timing.get('overruns', 0)}",
    ]
    health = status.get("health") or {}
    if health:
        lines.append("devices     " + ", ".join(f"{k} {v}" for k, v in sorted(health.items())))
    marking = status.get("marking") or {}
    marked = {place: tokens for place, tokens in marking.items() if tokens}
    lines.append("marking" + ("" if marked else "     (no tokens)"))
    records = status.get("tokens") or {}
    lines += [f"  {place:<24} {tokens}" + ("  " + ", ".join(
        json.dumps(r, sort_keys=True) for r in records[place]) if records.get(place) else "")
        for place, tokens in sorted(marked.items())]
    lines += _firings(status.get("net_live") or {})
    lines += [f"waiting     {_waited(w)}" for w in (status.get("waiting") or [])[:1]]
    if kept := status.get("kept_across"):  # docs/retain.md, a program's own values
        lines.append(f"kept        from {kept.get('from')}: {', '.join(kept.get('symbols'))}")
    forced = status.get("forced") or {}
    lines.append("forced" + ("      (nothing)" if not forced else ""))
    if forced:  # imported here: core/present.py needs numpy, which a client does not load
        from softplc.core.present import text_of
    symbols = status.get("symbols") or {}  # the value as core/present.py writes it, unit too
    lines += [f"  {name:<24} {text_of(symbols.get(name) or {}, value)}  FORCED"
              for name, value in sorted(forced.items())]
    if status.get("diagnostic_count"):
        lines.append(f"diagnostics {status['diagnostic_count']} run-time error(s) of guards "
                     "and actions (the last shown)")
    lines += [f"diagnostic  {d}" for d in status.get("diagnostics") or []]
    if failure := (status.get("compile_process") or {}).get("last_failure"):
        lines.append(f"compiler    {failure}")  # a refused download's reason, kept
    return "\n".join(lines)


def _waited(wait: dict[str, Any]) -> str:
    """The longest wait of the running net (core/waiting.py), from its status document."""
    what = wait.get("transition") or "(the net)"
    return f"{what} for {wait.get('for_s', 0):.1f} s: {'; '.join(wait.get('blockers') or [])}"


def _firings(live: dict[str, Any]) -> list[str]:
    """Timed firings in progress (`duration`: tokens consumed, production due), with the
    time left; a net too large for the board only gives their number."""
    busy = live.get("busy") or {}
    if not isinstance(busy, dict):
        return [f"firing      {busy} timed firing(s) in progress"]
    return [f"firing      {name}: {_ms(times.get('remaining_ms'))} left of "
            f"{_ms(times.get('duration_ms'))}" for name, times in sorted(busy.items())]


def _ms(value: Any) -> str:
    if not isinstance(value, int | float):
        return "?"
    return f"{value / 1000:.3g} s" if value >= 1000 else f"{value:g} ms"


def _us(value: Any) -> str:
    if not isinstance(value, int | float):
        return "?"
    return f"{value / 1000:.3g} ms" if value >= 10_000 else f"{value:.0f} µs"
