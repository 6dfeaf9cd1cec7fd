"""`softplc run`'s Sparkplug options (docs/sparkplug.md) and the configuration they make.

Owns: the options, the password from --sparkplug-password-file or SOFTPLC_SPARKPLUG_PASSWORD
(so that it does not show in `ps`; either wins over the URL's), their checks (a clear error
before anything starts), and the process entry handed to the supervisor with the
configuration (runtime never imports this room).
Does not know: URLs (config.py), MQTT, payloads.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Final

from softplc.security.roles import Role
from softplc.sparkplug.config import SparkplugConfig, parse_url

PASSWORD_ENV: Final = "SOFTPLC_SPARKPLUG_PASSWORD"


def _url(text: str) -> SparkplugConfig:
    try:
        return parse_url(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _role(text: str) -> Role:
    try:
        return Role.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_options(run: argparse.ArgumentParser) -> None:
    """The `softplc run` options of the edge node (docs/sparkplug.md)."""
    run.add_argument("--sparkplug", type=_url, metavar="URL", default=None,
                     help="be a Sparkplug B edge node on this MQTT broker: "
                     "mqtt://[USER@]HOST:PORT/GROUP/EDGE_NODE or mqtts:// (default: off; "
                     "docs/sparkplug.md)")
    run.add_argument("--sparkplug-ca", metavar="FILE",
                     help="CA certificate(s) the mqtts:// broker's certificate must chain to "
                     "(default: the system's)")
    run.add_argument("--sparkplug-password-file", metavar="FILE",
                     help=f"the broker password, first line of FILE (or env {PASSWORD_ENV}; "
                     "default: the URL's, if any)")
    run.add_argument("--sparkplug-role", type=_role, default=Role.VIEWER, metavar="ROLE",
                     help="the role of commands that come by NCMD/DCMD: viewer (none), "
                     "operator (symbol writes; start/stop/resume with --sparkplug-commands), "
                     "engineer (also reset) (default: viewer)")
    run.add_argument("--sparkplug-commands", action="store_true",
                     help="accept program commands (start/stop/resume/reset) by NCMD "
                     "(default: refused)")
    run.add_argument("--sparkplug-primary-host", metavar="HOST_ID",
                     help="wait for this primary host's STATE online before births; NDEATH "
                     "and reconnect when it goes offline (default: none)")
    run.add_argument("--sparkplug-interval", type=float, default=0.1, metavar="SECONDS",
                     help="NDATA at most this often, changed metrics only (default: 0.1)")
    run.add_argument("--sparkplug-deadband", type=float, default=0.0, metavar="X",
                     help="a real metric is reported when it moved more than X (default: 0)")


def from_args(args: Any) -> SparkplugConfig | None:
    """The full configuration from `softplc run`'s arguments (None: off). ValueError for a
    password file that cannot be read, a bad interval or deadband."""
    base = getattr(args, "sparkplug", None)
    if not isinstance(base, SparkplugConfig):
        return None
    password = base.password
    if os.environ.get(PASSWORD_ENV):
        password = os.environ[PASSWORD_ENV]
    if (path := getattr(args, "sparkplug_password_file", None)) is not None:
        try:
            password = Path(path).read_text(encoding="utf-8").splitlines()[0]
        except (OSError, UnicodeDecodeError, IndexError) as exc:
            raise ValueError(f"--sparkplug-password-file {path}: cannot read its first line "
                             f"({exc or 'empty file'})") from None
    interval = float(args.sparkplug_interval)
    deadband = float(args.sparkplug_deadband)
    if not 0.0 <= interval <= 3600.0:
        raise ValueError(f"--sparkplug-interval {interval:g}: expected 0..3600 seconds")
    if not deadband >= 0.0:
        raise ValueError(f"--sparkplug-deadband {deadband:g}: expected a number >= 0")
    ca = getattr(args, "sparkplug_ca", None)
    if ca is not None and not Path(ca).is_file():
        raise ValueError(f"--sparkplug-ca {ca}: no such file")
    from softplc.sparkplug.process import process_main  # the runtime: only when it is on

    return replace(base, password=password, ca_file=ca, role=args.sparkplug_role,
                   commands=bool(args.sparkplug_commands), tls=base.tls or ca is not None,
                   primary_host=args.sparkplug_primary_host, interval_s=interval,
                   deadband=deadband, state_dir=str(args.state_dir), main=process_main)
