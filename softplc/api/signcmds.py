"""The CLI of signed programs: `softplc keys new|list|trust`, `softplc sign [--version N]`,
and the signature options of `softplc download` (--sign-key, --version, --signature,
--allow-older).

Owns: where an engineer's keys live (--dir, default $XDG_CONFIG_HOME/softplc/keys), what
`softplc download` sends for a program (its bundle, or its text when its files are not all
here; a bundle zip as it is), and so what `softplc sign` signs: exactly those bytes, into
FILE.sig. Does not know: HTTP (client.py), Ed25519 (security/signing.py).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
from pathlib import Path
from typing import Final

from softplc.api.secopts import TRUSTED_DIR
from softplc.program import bundle as bundles

EXIT_OK: Final = 0
EXIT_REFUSED: Final = 1
SIG_SUFFIX: Final = ".sig"


def keys_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "softplc" / "keys"


def add_keys(keys: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    verbs = keys.add_subparsers(dest="verb", required=True, metavar="VERB",
                                help="new, list or trust")
    new = verbs.add_parser("new", help="make a key pair NAME.key (private, 0600) and NAME.pub "
                           "(what a PLC trusts)")
    new.add_argument("name", help="the key's name: the signer status names (a-z 0-9 _ -)")
    listed = verbs.add_parser("list", help="the key pairs in --dir and their fingerprints")
    for parser in (new, listed):
        parser.add_argument("--dir", metavar="DIR", type=Path, default=None,
                            help=f"where the keys are (default: {keys_dir()})")
    trust = verbs.add_parser("trust", help="copy a public key into a PLC's trusted keys: "
                             "downloads must then be signed by a trusted key")
    trust.add_argument("public_key", type=Path, help="NAME.pub (the signer is called NAME)")
    trust.add_argument("--state-dir", metavar="DIR", default="state",
                       help="the PLC's state directory (default: %(default)s)")
    trust.add_argument("--trusted-keys", metavar="DIR", default=None,
                       help=f"the PLC's --trusted-keys (default: STATE_DIR/{TRUSTED_DIR})")
    keys.set_defaults(func=cmd_keys)


def add_sign(sign: argparse.ArgumentParser) -> None:
    sign.add_argument("program", help="a program file (YAML) or a bundle (.zip)")
    sign.add_argument("--key", required=True, help="a private key file, or the NAME of one in "
                      f"{keys_dir()} (required)")
    _version_option(sign, "")
    sign.add_argument("-o", "--output", metavar="FILE", default=None,
                      help="where the signature goes (default: PROGRAM.sig)")
    sign.set_defaults(func=cmd_sign)


def _version_option(parser: argparse.ArgumentParser, only: str) -> None:
    parser.add_argument("--version", metavar="N", type=int, default=None,
                        help=f"{only}sign the program's version N (a whole number >= 0) with "
                        "it: a PLC refuses a signed version older than the one it runs "
                        "unless --allow-older (default: unversioned, taken as version 0)")


def add_download_options(download: argparse.ArgumentParser) -> None:
    given = download.add_mutually_exclusive_group()
    given.add_argument("--sign-key", metavar="KEY", default=None,
                       help="sign what is sent with this private key (a file, or a NAME in "
                       f"{keys_dir()}) (default: unsigned, or --signature)")
    given.add_argument("--signature", metavar="FILE", default=None,
                       help="send this signature (softplc sign's PROGRAM.sig, with its "
                       "version) (default: none)")
    _version_option(download, "with --sign-key: ")
    download.add_argument("--allow-older", action="store_true",
                          help="take a signed version older than the one the PLC runs: a "
                          "rollback an engineer decides, named in the audit trail (default: "
                          "refused)")


def download_body(program: str) -> tuple[bytes, bool, list[Path]]:
    """What `softplc download PROGRAM` sends: (the bytes, a bundle?, files not found here
    and so resolved by the server: then the text goes alone)."""
    raw = Path(bundles.file_of(program)).read_bytes()
    if bundles.is_bundle(raw):
        return raw, True, []
    raw.decode("utf-8")  # UnicodeDecodeError: not a program
    absent = bundles.missing(program)
    if absent:
        return raw, False, absent
    return bundles.pack(bundles.from_files(program)), True, []


def private_key_path(key: str) -> Path:
    path = Path(key)
    return path if path.exists() or os.sep in key else keys_dir() / f"{key}.key"


def signature_for(args: argparse.Namespace, body: bytes) -> str | None:
    """The signature line to send with `body`: made with --sign-key, or read from
    --signature; None without either. Raises SigningError or OSError."""
    from softplc.security import signing

    version = getattr(args, "version", None)
    if getattr(args, "sign_key", None):
        return signing.sign(body, signing.load_private(private_key_path(args.sign_key)),
                            version)
    if version is not None:
        raise signing.SigningError("--version goes with --sign-key (a --signature file "
                                   "carries the version it was signed with)")
    if getattr(args, "signature", None):
        line = Path(args.signature).read_text(encoding="ascii").strip()
        signing.Signature.parse(line)  # malformed: said here, not by the PLC
        return line
    return None


def cmd_sign(args: argparse.Namespace) -> int:
    from softplc.security import signing

    try:
        body, is_bundle, absent = download_body(args.program)
        line = signing.sign(body, signing.load_private(private_key_path(args.key)),
                            args.version)
        out = Path(args.output or args.program + SIG_SUFFIX)
        out.write_text(line + "\n", encoding="ascii")
    except (OSError, UnicodeDecodeError, bundles.BundleError, signing.SigningError) as exc:
        print(f"softplc sign: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    what = "bundle" if is_bundle else "text (its files are not all here: " + \
        ", ".join(map(str, absent)) + ")"
    version = "unversioned" if args.version is None else f"version {args.version}"
    print(f"{out}: {line.split()[1]} signed the {what}, {len(body)} bytes, SHA-256 "
          f"{hashlib.sha256(body).hexdigest()}, {version}")
    print(f"send it: softplc download {args.program} --signature {out}")
    return EXIT_OK


def cmd_keys(args: argparse.Namespace) -> int:
    from softplc.security import signing

    try:
        if args.verb == "new":
            private, public = signing.new_key_pair(args.dir or keys_dir(), args.name)
            print(f"private key {private} (0600: keep it to yourself)")
            print(f"public key  {public}  {signing.fingerprint(signing.load_public(public))}")
            print(f"on the PLC: softplc keys trust {public.name} --state-dir STATE_DIR")
        elif args.verb == "list":
            for public in sorted((args.dir or keys_dir()).glob("*.pub")):
                print(f"{public.stem:<20} {signing.fingerprint(signing.load_public(public))}")
        else:
            signing.check_name(args.public_key.stem)
            key = signing.load_public(args.public_key)
            target = Path(args.trusted_keys or Path(args.state_dir) / TRUSTED_DIR)
            target.mkdir(mode=0o700, parents=True, exist_ok=True)
            shutil.copyfile(args.public_key, target / f"{args.public_key.stem}.pub")
            print(f"{target / args.public_key.name}: {args.public_key.stem} "
                  f"{signing.fingerprint(key)} trusted; downloads must now be signed")
    except (OSError, signing.SigningError) as exc:
        print(f"softplc keys {args.verb}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    return EXIT_OK
