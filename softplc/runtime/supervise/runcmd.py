"""`softplc run` as a command: check that it can start, start the supervisor, print the banner
and a live status line, stop on Ctrl-C or SIGTERM, and end with an exit code.

Owns: the startup checks (program, ports, state directory) with one clear line each, the
signal handlers, the console output, systemd notifications, and the exit codes.
Does not know: how processes are started, watched and healed (supervisor.py does).

Exit codes (docs/operations.md): 0 stopped on request (SIGTERM, SIGINT, --duration); 1 could
not start (program, port, state directory); 2 bad command line; 3 gave up: the scan process
died more than SCAN_RESTARTS times within RESTART_WINDOW_S.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shlex
import signal
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.api import secopts
from softplc.core.problems import ProgramError
from softplc.runtime.prepare import CompilerFailed
from softplc.runtime.retain.writer import StateDirBusy, check_state_dir
from softplc.runtime.shared.procs import name_process
from softplc.runtime.supervise.leftovers import remove_stale_segments
from softplc.runtime.supervise.sdnotify import Notifier
from softplc.runtime.supervise.startprog import StartProgram, StartRequest, compile_start
from softplc.runtime.supervise.supervisor import (
    RESTART_WINDOW_S,
    SCAN_RESTARTS,
    STOP_S,
    GaveUp,
    Supervisor,
)
from softplc.security import preflight
from softplc.security.auth import TOKEN_FILE, is_loopback

EXIT_OK, EXIT_START, EXIT_USAGE, EXIT_GAVE_UP = 0, 1, 2, 3
BOOT_POLICIES = ("stop", "warm", "cold")  # docs/retain.md, boot policy
BOOT_POLICY_FILE = "boot_policy"  # in the state directory: the installation's choice


def status_line(doc: dict[str, Any]) -> str:
    timing = doc.get("timing", {})
    marked = ",".join(sorted(doc.get("marking", {}))) or "-"
    return (f"{doc.get('state', '?'):8} scans={doc.get('scan_count', 0):<8} "
            f"period={doc.get('period_us', 0) / 1000:g}ms "
            f"p99_late={timing.get('p99_lateness_us', 0):.0f}us "
            f"overruns={timing.get('overruns', 0)} marked={marked}")


def host_port(host: str, port: int) -> str:
    """HOST:PORT as URLs and `--api` write it: an IPv6 address in brackets ([::1]:8080)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _port_in_use(endpoint: tuple[str, int] | None) -> str | None:
    if endpoint is None or endpoint[1] == 0:
        return None
    with socket.socket(socket.AF_INET6 if ":" in endpoint[0] else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(endpoint)
        except OSError as exc:
            return f"{host_port(*endpoint)}: {exc.strerror}"
    return None


def try_api(args: argparse.Namespace) -> list[str]:
    """A curl command for the API's status that works as printed, on this machine: a
    wildcard bind asked on loopback, an https one verified against the PLC's certificate,
    the owner's key sent where a key is needed (a bind that is not loopback: auth.py)."""
    host, port = args.api
    host = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    scheme = getattr(args, "api_scheme", "http")
    command = ["curl", "-sS"]
    if cert := getattr(args, "api_cert", ""):
        command += ["--cacert", cert]
    if not is_loopback(args.api[0]):
        token = (Path(args.state_dir) / TOKEN_FILE).resolve()
        command += ["-H", f"Authorization: Bearer $(cat {shlex.quote(str(token))})"]
    return [*command, f"{scheme}://{host_port(host, port)}/api/v1/status"]


def _shell_words(command: list[str]) -> str:
    """`command` to paste into a shell: a header that reads a file stays in double quotes."""
    return " ".join(f'"{word}"' if "$(" in word else shlex.quote(word) for word in command)


def _startup_problem(args: argparse.Namespace, start: StartProgram | None) -> str | None:
    """The first reason `softplc run` cannot start, as one line; None when it can."""
    if start is not None and start.conflict:
        return start.conflict
    for what, endpoint in (("Modbus", args.modbus), ("API", args.api)):
        if problem := _port_in_use(endpoint):
            return f"{what} port {problem} (another softplc? choose another with --{what.lower()})"
    state = Path(args.state_dir)
    try:
        state.mkdir(parents=True, exist_ok=True)
        probe = state / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        return (f"state directory {state} is not usable: {exc.strerror} "
                "(choose one with --state-dir)")
    return None


def resolve_boot_policy(args: argparse.Namespace) -> str | None:
    """The installation's boot policy (docs/retain.md): `--boot-policy` is kept in the state
    directory, so that a restart without it keeps it; else the kept one; else "stop" (a PLC
    next to a machine does not start it on its own after a power loss). Sets
    `args.boot_policy` and `args.boot_policy_source`; returns why it cannot keep it, or None."""
    path = Path(args.state_dir) / BOOT_POLICY_FILE
    given = getattr(args, "boot_policy", None)
    if given is not None:
        try:
            temp = path.with_name(f".{BOOT_POLICY_FILE}.{os.getpid()}.tmp")
            with temp.open("w") as out:
                out.write(given + "\n")
                out.flush()
                os.fsync(out.fileno())
            temp.replace(path)
        except OSError as exc:
            return f"boot policy not kept in {path}: {exc.strerror or exc}"
        args.boot_policy_source = f"--boot-policy, kept in {path}"
        return None
    try:
        kept = path.read_text().strip()
    except FileNotFoundError:
        kept = None
    except (OSError, UnicodeDecodeError) as exc:
        kept = f"unreadable ({exc})"
    if kept in BOOT_POLICIES:
        args.boot_policy, args.boot_policy_source = kept, f"kept in {path}"
        return None
    args.boot_policy, args.boot_policy_source = "stop", "default"
    if kept is not None:  # bad content: the safe default, said where the operator looks
        args.boot_policy_source = f"default ({path} holds {kept[:40]!r}, not one of " \
                                  f"{', '.join(BOOT_POLICIES)})"
        print(f"softplc: warning: boot policy {args.boot_policy_source}", file=sys.stderr)
    return None


def _security_files_usable(args: argparse.Namespace) -> bool:
    """One line per security file that is corrupt, truncated or unreadable (issue 38): the
    start refused for those a service cannot start without, a warning for the others (the
    service starts closed)."""
    state_dir = Path(args.state_dir)
    found = preflight.check(state_dir, secopts.load(state_dir),
                            opcua=bool(getattr(args, "opcua", None)))
    for line in found.warnings:
        print(f"softplc: warning: {line}", file=sys.stderr)
    for line in found.refused:
        print(f"softplc: {line}", file=sys.stderr)
    return not found.refused


def run(args: argparse.Namespace) -> int:
    if not (args.watchdog > 0 and math.isfinite(args.watchdog)):  # its budget: period x this
        print(f"softplc: --watchdog must be a number above 0, got {args.watchdog:g}",
              file=sys.stderr)
        return EXIT_USAGE
    start = None  # compiled once, here or in a compile process; every scan process loads it
    if args.program:
        try:
            start = compile_start(StartRequest(args.program, args.plant),
                                  getattr(args, "verify", "warn"))
        except ProgramError as exc:
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            return EXIT_START
        except CompilerFailed as exc:
            print(f"softplc: {exc}", file=sys.stderr)
            return EXIT_START
    try:
        check_state_dir(args.state_dir)  # the scan process takes the lock; fail early and clearly
    except StateDirBusy as exc:
        print(f"softplc: {exc}", file=sys.stderr)
        return EXIT_START
    if trouble := _startup_problem(args, start):
        print(f"softplc: {trouble}", file=sys.stderr)
        return EXIT_START
    if trouble := resolve_boot_policy(args) or secopts.prepare(args):  # TLS, trusted keys
        print(f"softplc: {trouble}", file=sys.stderr)
        return EXIT_START
    if not _security_files_usable(args):
        return EXIT_START
    remove_stale_segments()
    try:
        supervisor = Supervisor.from_args(args)
        supervisor.loop_config = dataclasses.replace(supervisor.loop_config, compiled=start)
    except ValueError as exc:  # --rt-priority or --scan-cpu out of range
        print(f"softplc: {exc}", file=sys.stderr)
        return EXIT_USAGE
    name_process("softplc")  # `python` in ps when started as `python -m softplc`
    stopping = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stopping
        stopping = True
        # The scan process drives the outputs safe the moment it hears, not when this main
        # thread next looks (it may be spawning a service, printing, or waiting 50 ms).
        supervisor.stop_scan.tell()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        supervisor.start(stopping=lambda: stopping)
    except RuntimeError as exc:
        print(f"softplc: {exc}", file=sys.stderr)
        supervisor.stop()
        return EXIT_START
    notifier = Notifier()
    notifier.send(f"READY=1\nMAINPID={os.getpid()}\nSTATUS=scanning")
    _banner(args, supervisor.status())
    print(f"  scan process pid {supervisor.scan.pid} ({supervisor.status().get('realtime', '?')}), "
          f"{supervisor.pids()}", flush=True)
    print(f"  supervisor pid {os.getpid()}: SIGTERM or SIGINT stops everything within "
          f"{STOP_S:g} s; exit code 0 then, 3 if it gives up restarting", flush=True)
    return _supervise(supervisor, args, lambda: stopping, notifier)


def _supervise(supervisor: Supervisor, args: argparse.Namespace,
               stopping: Callable[[], bool], notifier: Notifier) -> int:
    began = time.monotonic()
    tty = sys.stdout.isatty() and not args.quiet
    last_print = 0.0
    code = EXIT_OK
    try:
        while not stopping():
            time.sleep(0.05)
            if stopping():  # a signal during the sleep: the children may be ending already
                break  # (a group's SIGTERM reaches them too), which is no death to heal
            try:
                said = supervisor.watch()
            except GaveUp as exc:
                print(("\n" if tty else "") + f"softplc: {exc}", file=sys.stderr, flush=True)
                code = EXIT_GAVE_UP
                break
            for line in said:
                print(("\n" if tty else "") + f"softplc: {line}", file=sys.stderr, flush=True)
                notifier.send(f"STATUS={line}")
            now = time.monotonic()
            notifier.ping(now)
            if args.duration and now - began >= args.duration / 1e9:
                break
            if tty:
                print("\r" + status_line(supervisor.status())[:150].ljust(150), end="", flush=True)
            elif not args.quiet and now - last_print >= 5:
                print(status_line(supervisor.status()), flush=True)
                last_print = now
    finally:
        notifier.send("STOPPING=1")
        supervisor.stop()
        final = supervisor.final
    ending = "gave up" if code else "stopped"
    print(("\n" if tty else "") + f"{ending}: " + status_line(final) + ", outputs safe",
          flush=True)
    return code


def _banner(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    print(f"softplc running {args.program or '(no program)'}"
          f" (period {args.period / 1e6:g} ms){' started' if args.start else ''}")
    print(f"  {doc.get('start_mode', '?')} start: {doc.get('start_reason', '?')}")
    print(f"  boot policy {doc.get('boot_policy', '?')} ({doc.get('boot_policy_source', '?')})")
    print(f"  program: {doc.get('program_source', '?')}; restarts: scan process restarted "
          f"warm from the newest snapshot, at most {SCAN_RESTARTS} times in "
          f"{RESTART_WINDOW_S:g} s")
    interval = getattr(args, "retain_interval", 0)
    print(f"  retain in {args.state_dir}/: "
          + (f"every {interval / 1e9:g} s and on stop" if interval else "on stop only"))
    if args.modbus:
        host, port = args.modbus
        print(f"  Modbus TCP slave on {host}:{port}; try: "
              f"mbpoll -m tcp -p {port} -a 1 -0 -1 -t 0 -r 0 -c 8 {host}")
    if args.api:
        print(f"  HTTP API on {getattr(args, 'api_scheme', 'http')}://{host_port(*args.api)}; "
              f"try: {_shell_words(try_api(args))}"
              + (f"\n  TLS: {args.api_tls}" if getattr(args, "api_tls", "") else ""))
    if getattr(args, "opcua", None):
        print(f"  OPC UA server on opc.tcp://{host_port(*args.opcua)} (writes and methods: "
              "user token)")
    print("  Ctrl-C stops (outputs to their safe values first)", flush=True)
