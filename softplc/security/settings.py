"""The security settings `softplc run` was started with, for every service of the PLC: HTTPS
(the API's TLS mode and certificate) and the directory of the keys whose signatures
downloads need. `softplc run` writes them to STATE_DIR/security.json at every start; the HTTP
and OPC UA services read them there (absent: plain HTTP and STATE_DIR/trusted_keys, as for
a service started on its own).

Owns: SecuritySettings, the file's format, `save` and `load` (an edited, unreadable file is
read as the safe side: TLS on).
Does not know: argparse (api/secopts.py), certificates (tls.py), signatures.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from softplc.security.tls import MODES, Mode, TlsSettings

SETTINGS_FILE: Final = "security.json"
TRUSTED_DIR: Final = "trusted_keys"  # in the state directory, unless --trusted-keys


@dataclass(frozen=True, slots=True)
class SecuritySettings:
    tls: TlsSettings = field(default_factory=TlsSettings)
    trusted_keys: str | None = None  # None: STATE_DIR/trusted_keys

    def trusted_dir(self, state_dir: Path) -> Path:
        return Path(self.trusted_keys) if self.trusted_keys else Path(state_dir) / TRUSTED_DIR


def save(state_dir: Path, settings: SecuritySettings) -> None:
    state_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    data = {"tls": {"mode": settings.tls.mode, "cert": settings.tls.cert,
                    "key": settings.tls.key}, "trusted_keys": settings.trusted_keys}
    fd, tmp = tempfile.mkstemp(dir=state_dir, prefix=f".{SETTINGS_FILE}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            json.dump(data, out)
        os.replace(tmp, state_dir / SETTINGS_FILE)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(state_dir: Path) -> SecuritySettings:
    """What the last `softplc run` on `state_dir` asked for; the defaults without it."""
    try:
        data: Any = json.loads((Path(state_dir) / SETTINGS_FILE).read_text(encoding="utf-8"))
        tls = data["tls"]
        mode: Mode = tls["mode"] if tls["mode"] in MODES else "on"  # edited: the safe side
        return SecuritySettings(TlsSettings(mode, _text(tls.get("cert")), _text(tls.get("key"))),
                                _text(data.get("trusted_keys")))
    except FileNotFoundError:
        return SecuritySettings()
    except (OSError, ValueError, KeyError, TypeError):
        return SecuritySettings(TlsSettings("on"))



def _text(value: object) -> str | None:
    return value if isinstance(value, str) and value else None
