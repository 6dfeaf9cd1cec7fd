"""The CLI's local administration: `softplc users add|list|passwd|role|key|remove` and
`softplc audit [--since TIME] [--verify]`.

Owns: their arguments, reading passwords (the terminal without echo, or one line of stdin
when it is not a terminal: never the command line), what a person reads, exit codes (0
done, 1 refused, a broken audit chain or one that records a break), and the audit records of
user changes made here.
They act on the files of --state-dir directly, as the account that owns it; a running PLC
sees the change at its next request.
Does not know: HTTP, the PLC.
"""

from __future__ import annotations

import argparse
import getpass
import json
import os
import sys
from typing import Any, Final

from softplc.security.audit import AuditTrail, parse_since
from softplc.security.roles import Role
from softplc.security.users import OWNER, UserError, UserStore

EXIT_OK: Final = 0
EXIT_REFUSED: Final = 1
_NAME_HELP: Final = "the user's name: 1 to 32 of a-z 0-9 _ -, starting with a letter"
_STATE_HELP: Final = "the PLC's state directory, as given to softplc run (default: %(default)s)"


def add_users(users: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    verbs = users.add_subparsers(dest="verb", required=True, metavar="VERB",
                                 help="add, list, passwd, role, key or remove")
    add = verbs.add_parser("add", help="add a user; the password is read from the terminal "
                           "(or one line of stdin)")
    add.add_argument("name", help=_NAME_HELP)
    add.add_argument("--role", required=True, choices=[r.label for r in Role],
                     help="what the user may do (required)")
    verbs.add_parser("list", help="users, roles, whether they have an API key")
    passwd = verbs.add_parser("passwd", help="set a user's password (read as for add)")
    passwd.add_argument("name", help=_NAME_HELP)
    role = verbs.add_parser("role", help="change a user's role")
    role.add_argument("name", help=_NAME_HELP)
    role.add_argument("role", choices=[r.label for r in Role], help="the new role")
    key = verbs.add_parser("key", help="make a user's API key (printed once; the previous "
                           "one stops working), or --revoke it")
    key.add_argument("name", help=_NAME_HELP)
    key.add_argument("--revoke", action="store_true", help="remove the key (default: off)")
    remove = verbs.add_parser("remove", help="remove a user (their key and sessions end)")
    remove.add_argument("name", help=_NAME_HELP)
    for parser in (add, verbs.choices["list"], passwd, role, key, remove):
        parser.add_argument("--state-dir", metavar="DIR", default="state", help=_STATE_HELP)
    users.set_defaults(func=cmd_users)


def add_audit(audit: argparse.ArgumentParser) -> None:
    audit.add_argument("--since", metavar="TIME", default=None,
                       help="records at or after TIME: ISO (2025-03-01T08:00Z; UTC without a "
                       "zone) or a duration back from now (2h) (default: all)")
    audit.add_argument("--verify", action="store_true",
                       help="check the chain: exit 1 naming the first bad record, or every "
                       "break of the trail recorded in it (default: off)")
    audit.add_argument("--json", action="store_true",
                       help="print the records as JSON lines (default: a table)")
    audit.add_argument("--state-dir", metavar="DIR", default="state", help=_STATE_HELP)
    audit.set_defaults(func=cmd_audit)


def read_password(confirm: bool) -> str:
    """From the terminal without echo (twice when `confirm`), else one line of stdin."""
    if not sys.stdin.isatty():
        return sys.stdin.readline().removesuffix("\n").removesuffix("\r")
    first = getpass.getpass("password: ")
    if confirm and getpass.getpass("again: ") != first:
        raise UserError("the two passwords differ; nothing changed")
    return first


def cmd_users(args: argparse.Namespace) -> int:
    store = UserStore(args.state_dir)
    try:
        message = _USERS[args.verb](store, args)
    except UserError as exc:
        print(f"softplc users {args.verb}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    except OSError as exc:
        print(f"softplc users {args.verb}: {args.state_dir}: {exc.strerror}", file=sys.stderr)
        return EXIT_REFUSED
    if message is not None:
        print(message)
    return EXIT_OK


def _add(store: UserStore, args: argparse.Namespace) -> str:
    user = store.add(args.name, Role.parse(args.role), read_password(confirm=True))
    _audit(args, "users add", user.name, {"role": user.role.label})
    return f"user {user.name} added ({user.role.label})"


def _list(store: UserStore, args: argparse.Namespace) -> str:
    rows = [f"{'name':<24} {'role':<9} {'key':<4} created",
            f"{OWNER:<24} {'admin':<9} {'yes':<4} (built in: STATE_DIR/api_token)"]
    rows += [f"{u.name:<24} {u.role.label:<9} {'yes' if u.key_sha256 else 'no':<4} {u.created}"
             for u in sorted(store.users().values(), key=lambda u: u.name)]
    return "\n".join(rows)


def _passwd(store: UserStore, args: argparse.Namespace) -> str:
    store.set_password(args.name, read_password(confirm=True))
    _audit(args, "users passwd", args.name)
    return f"password of {args.name} changed"


def _role(store: UserStore, args: argparse.Namespace) -> str:
    store.set_role(args.name, Role.parse(args.role))
    _audit(args, "users role", args.name, {"role": args.role})
    return f"{args.name} is now {args.role}"


def _key(store: UserStore, args: argparse.Namespace) -> str:
    if args.revoke:
        store.revoke_key(args.name)
        _audit(args, "users key revoke", args.name)
        return f"API key of {args.name} revoked"
    key = store.new_key(args.name)
    _audit(args, "users key", args.name)
    print(f"API key of {args.name} (shown once; send it as `Authorization: Bearer KEY`, or "
          f"give it to --token or ${'SOFTPLC_API_TOKEN'}):", file=sys.stderr)
    return key


def _remove(store: UserStore, args: argparse.Namespace) -> str:
    store.remove(args.name)
    _audit(args, "users remove", args.name)
    return f"user {args.name} removed"


_USERS: Final = {"add": _add, "list": _list, "passwd": _passwd, "role": _role, "key": _key,
                 "remove": _remove}


def _audit(args: argparse.Namespace, action: str, target: str,
           detail: dict[str, Any] | None = None) -> None:
    try:
        account = getpass.getuser()
    except (KeyError, OSError):
        account = str(os.geteuid())
    AuditTrail(args.state_dir).append({
        "user": OWNER, "role": Role.ADMIN.label, "via": f"account {account}", "peer": "local",
        "iface": "cli", "action": f"{action} {target}", "outcome": "applied", "status": 0,
        "detail": detail or {}})


def cmd_audit(args: argparse.Namespace) -> int:
    trail = AuditTrail(args.state_dir)
    if args.verify:
        return _verify(trail)
    try:
        since = parse_since(args.since) if args.since else None
    except ValueError as exc:
        print(f"softplc audit: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    for record in trail.records(since):
        print(json.dumps(record, sort_keys=True) if args.json else format_record(record))
    return EXIT_OK


def _verify(trail: AuditTrail) -> int:
    """Exit 1 for a broken chain, and for one that links but records a break: a writer
    found records gone or changed, so the trail is no longer the whole evidence."""
    verdict = trail.verify()
    counts = (f"{verdict.records} record(s), seq {verdict.first_seq}..{verdict.last_seq}, "
              f"last hash {verdict.last_hash[:16]}")
    if verdict.ok:
        print(f"audit trail ok: {counts}")
        return EXIT_OK
    if verdict.breaks and verdict.where == verdict.breaks[0][0]:  # it links but for them
        print(f"softplc audit: the chain links ({counts}), but records {len(verdict.breaks)} "
              "break(s) of the trail: records before each were cut or rewritten", file=sys.stderr)
    else:
        print(f"softplc audit: chain BROKEN at {verdict.where} (the record after seq "
              f"{verdict.last_seq}, {verdict.records} good before it): {verdict.problem}",
              file=sys.stderr)
    for where, what in verdict.breaks:
        print(f"  break at {where} {what}", file=sys.stderr)
    return EXIT_REFUSED


def format_record(record: dict[str, Any]) -> str:
    """One record as a line: time, seq, who (user/role@peer via iface), what, outcome."""
    if "unreadable" in record:
        return f"(unreadable line {record['unreadable']})"
    who = f"{record.get('user') or '-'}/{record.get('role') or '-'}@{record.get('peer') or '-'}"
    detail = record.get("detail") or {}
    extra = " ".join(f"{k}={json.dumps(v)}" for k, v in sorted(detail.items()))
    return (f"{record.get('time', '?')} #{record.get('seq', '?')} {who} {record.get('iface')}: "
            f"{record.get('action')} -> {record.get('outcome')} ({record.get('status')})"
            + (f" {extra}" if extra else ""))
