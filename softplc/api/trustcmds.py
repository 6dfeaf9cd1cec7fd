"""The CLI's trust lists: `softplc trust list|accept NAME|remove NAME [--modbus]` (issue 31).

Owns: their arguments, what a person reads, exit codes (0 done, 1 refused), and the audit
records of changes made here. They act on STATE_DIR/pki (OPC UA's clients) or, with
--modbus, STATE_DIR/modbus-tls (Modbus/TCP Security's) directly, as the account that owns
it; a running server sees a change at the next connection it accepts.
Does not know: OPC UA, the PLC, how a certificate is checked (trust.py).
"""

from __future__ import annotations

import argparse
import getpass
import os
import sys
from typing import Final

from softplc.security.audit import AuditTrail
from softplc.security.roles import Role
from softplc.security.trust import Certificate, TrustError, TrustList
from softplc.security.users import OWNER

MODBUS_TLS_DIR: Final = "modbus-tls"  # hmi/secure.py's, which this room may not import

EXIT_OK: Final = 0
EXIT_REFUSED: Final = 1
_STATE_HELP: Final = "the PLC's state directory, as given to softplc run (default: %(default)s)"


def add_trust(trust: argparse.ArgumentParser) -> None:
    """Add `trust`'s verbs to the parser cli/table.py made for it."""
    verbs = trust.add_subparsers(dest="verb", required=True, metavar="VERB",
                                 help="list, accept or remove")
    verbs.add_parser("list", help="trusted and rejected certificates")
    accept = verbs.add_parser("accept", help="trust a rejected certificate, or a certificate "
                              "file (DER or PEM)")
    accept.add_argument("name", help="a name from `softplc trust list` (or a unique start of "
                        "it, or of the thumbprint), or a file")
    remove = verbs.add_parser("remove", help="forget a trusted or rejected certificate")
    remove.add_argument("name", help="a name from `softplc trust list` (or a unique start)")
    for parser in (verbs.choices["list"], accept, remove):
        parser.add_argument("--state-dir", metavar="DIR", default="state", help=_STATE_HELP)
        parser.add_argument("--modbus", action="store_true", help="the Modbus/TCP Security "
                            f"port's clients (STATE_DIR/{MODBUS_TLS_DIR}), not OPC UA's")
    trust.set_defaults(func=cmd_trust)


def cmd_trust(args: argparse.Namespace) -> int:
    trust = (TrustList(args.state_dir, MODBUS_TLS_DIR) if getattr(args, "modbus", False)
             else TrustList(args.state_dir))
    try:
        if args.verb == "list":
            print(_table(trust.certificates()))
            return EXIT_OK
        entry = trust.accept(args.name) if args.verb == "accept" else trust.remove(args.name)
    except TrustError as exc:
        print(f"softplc trust {args.verb}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    except OSError as exc:
        print(f"softplc trust {args.verb}: {exc.filename or args.state_dir}: {exc.strerror}",
              file=sys.stderr)
        return EXIT_REFUSED
    _audit(args, f"trust {args.verb} {entry.name}", entry)
    print(f"{entry.name} {'trusted' if args.verb == 'accept' else 'removed'} ({entry.subject})")
    return EXIT_OK


def _table(entries: list[Certificate]) -> str:
    if not entries:
        return "no client certificates (a refused one appears here as rejected)"
    rows = [f"{'name':<44} {'state':<9} {'valid until':<18} subject / ApplicationUri"]
    rows += [f"{c.name:<44} {c.state:<9} {c.not_after:<18} {c.subject} {c.uri}".rstrip()
             for c in entries]
    return "\n".join(rows)


def _audit(args: argparse.Namespace, action: str, entry: Certificate) -> None:
    try:
        account = getpass.getuser()
    except (KeyError, OSError):
        account = str(os.geteuid())
    AuditTrail(args.state_dir).append({
        "user": OWNER, "role": Role.ADMIN.label, "via": f"account {account}", "peer": "local",
        "iface": "cli", "action": action, "outcome": "applied", "status": 0,
        "detail": {"thumbprint": entry.thumbprint, "subject": entry.subject, "uri": entry.uri}})
