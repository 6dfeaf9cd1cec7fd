"""`softplc dap`: the Debug Adapter Protocol over stdio (as an editor launches an adapter) or
over TCP on 127.0.0.1 (`--port`, for VS Code's `debugServer`), one session at a time, each
attached to the PLC at `--api` (docs/debug.md, a debugger in the editor).

Owns: the command's arguments, the streams and the listening socket, a session's end (the
stream closed: its breakpoints removed, the PLC running on).
Does not know: what the messages mean (debug/dap.py), HTTP (api/client.py).
"""

from __future__ import annotations

import argparse
import socket
import sys
import threading
from typing import IO, Any

from softplc.api.admincmds import read_password
from softplc.api.clicmds import EXIT_OK, EXIT_REFUSED, EXIT_UNREACHABLE, connection_options
from softplc.api.client import ApiClient
from softplc.debug.dap import DapSession
from softplc.debug.dapwire import WireError, encode, read_message


def add_dap(dap: argparse.ArgumentParser) -> None:
    """Add `dap`'s arguments to the parser cli/table.py made for it."""
    dap.add_argument("--port", metavar="N", type=int, default=None,
                     help="serve DAP over TCP on 127.0.0.1:N, one session at a time (0: a free "
                     "port, said on stderr) (default: over stdin and stdout)")
    connection_options(dap)
    dap.set_defaults(func=cmd_dap)


def cmd_dap(args: argparse.Namespace) -> int:
    if args.user and args.port is None:
        print("softplc dap: --user needs --port (stdin carries the protocol)", file=sys.stderr)
        return EXIT_REFUSED
    try:
        password = read_password(confirm=False) if args.user else None
        client = ApiClient(args.api, args.token, args.timeout, state_dir=args.state_dir,
                           user=args.user, password=password, ca=args.ca)
    except ValueError as exc:  # a malformed --api URL
        print(f"softplc dap: {exc}", file=sys.stderr)
        return EXIT_UNREACHABLE
    try:
        if args.port is None:
            serve_stream(client, sys.stdin.buffer, sys.stdout.buffer)
        else:
            serve_tcp(client, args.port)
    except KeyboardInterrupt:
        pass
    except OSError as exc:  # the port is taken
        print(f"softplc dap: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    return EXIT_OK


def serve_stream(client: ApiClient, reader: IO[bytes], writer: IO[bytes]) -> None:
    """One session over a pair of byte streams, until `disconnect` or the end of `reader`."""
    lock = threading.Lock()

    def send(message: dict[str, Any]) -> None:
        data = encode(message)
        with lock:
            writer.write(data)
            writer.flush()

    session = DapSession(client, send)
    try:
        while not session.ended and (message := read_message(reader)) is not None:
            session.handle(message)
    except WireError as exc:
        print(f"softplc dap: {exc}", file=sys.stderr)
    except OSError:
        pass  # the editor went away: close() still cleans up
    finally:
        session.close()


def serve_tcp(client: ApiClient, port: int) -> None:
    """Sessions one after the other on 127.0.0.1:`port`, until interrupted."""
    with socket.create_server(("127.0.0.1", port)) as server:
        print(f"softplc dap: listening on 127.0.0.1:{server.getsockname()[1]}",
              file=sys.stderr, flush=True)
        while True:
            conn, _ = server.accept()
            with conn, conn.makefile("rb") as reader, conn.makefile("wb") as writer:
                serve_stream(client, reader, writer)
