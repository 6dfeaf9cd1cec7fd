"""Two signed downloads of the same version at once through two doors of one PLC (HTTP and
OPC UA: separate processes of a real `softplc run` on loopback): exactly one is taken.

The check of the running signed version and its advance are one decision (a turn, flock on
STATE_DIR/signed_version.lock, held from the check until the version is recorded), and a
version names one program: the other program signed with the running version is refused.
Before, both passed the check (each saw the version before either was recorded), both were
applied, and which program ran was whichever came last.
"""

from __future__ import annotations

import asyncio
import hashlib
import threading
from pathlib import Path

import pytest
from asyncua import ua

from softplc.security import signing, versions
from softplc.security.audit import AuditTrail
from tests.api.helpers import Answer, call
from tests.opcua.conftest import start_plc, stop_plc
from tests.security.test_doors_process import DRILLING, ROOT, _call, _client, _text
from tests.support import free_port

pytestmark = pytest.mark.slow  # a real softplc run with two doors
TRANSPORT = (ROOT / "programs" / "transport.yaml").read_text(encoding="utf-8")
VERSION = 5


def test_two_doors_one_version_exactly_one_program_taken(tmp_path: Path, keys: Path) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    (trusted / "alice.pub").write_bytes((keys / "alice.pub").read_bytes())
    state = tmp_path / "state"
    state.mkdir()
    api = f"http://127.0.0.1:{free_port()}"
    plc = start_plc("programs/drilling.yaml", state, "--trusted-keys", str(trusted),
                    "--api", api.removeprefix("http://"))
    alice = signing.load_private(keys / "alice.key")
    # two programs, each signed by alice as release 5 (the running one was not signed); each
    # alone is a download the PLC takes online, so the only refusal left is the version's
    # (a renamed drilling cell would be refused as another program on the same devices when
    # its door took the turn first)
    over_http = TRANSPORT.encode()
    over_opcua = (DRILLING + "# release b: same net, another body\n").encode()
    assert over_opcua != DRILLING.encode()
    http_line = signing.sign(over_http, alice, VERSION)
    opcua_line = signing.sign(over_opcua, alice, VERSION)
    start = threading.Barrier(2, timeout=60)
    answers: list[Answer] = []

    def http_download() -> None:
        start.wait()
        answers.append(call(api, "POST", "/api/v1/program?online=true", over_http,
                            {"Authorization": f"Bearer {plc.token}",
                             "X-Softplc-Signature": http_line}, timeout_s=120))

    async def opcua_download() -> ua.CallMethodResult:
        async with _client(plc, "owner", plc.token) as client:
            await asyncio.to_thread(start.wait)
            return await _call(client, "Download", _text(over_opcua.decode()),
                               ua.Variant(True, ua.VariantType.Boolean), _text("b.yaml"),
                               _text(opcua_line))

    sender = threading.Thread(target=http_download)
    try:
        sender.start()
        result = asyncio.run(opcua_download())
        sender.join(180)
    finally:
        stop_plc(plc.proc)
    assert len(answers) == 1
    http_taken = answers[0].status == 200
    opcua_taken = result.StatusCode.is_good()
    message = result.OutputArguments[0].Value if result.OutputArguments else ""
    assert http_taken != opcua_taken, (answers[0].status, answers[0].body, message)
    refusal = message if http_taken else answers[0].body["error"]
    assert refusal == (f"download refused: signed version {VERSION} is the running version, "
                       "of another program: a new release needs a higher version (an "
                       "engineer may pass --allow-older)"), refusal
    taken = over_http if http_taken else over_opcua
    running = versions.read(state)
    assert (running.version, running.body_sha256) == (VERSION, hashlib.sha256(taken).hexdigest())
    records = [r for r in AuditTrail(state).records()
               if r.get("action") in ("POST program", "Download")]
    assert sorted((r["action"], r["outcome"]) for r in records) == sorted(
        [("POST program", "applied" if http_taken else "refused"),
         ("Download", "applied" if opcua_taken else "refused")]), records
