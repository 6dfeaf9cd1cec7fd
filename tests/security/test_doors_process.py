"""The security model holds at every door of a real `softplc run` (issue 38): what one door
refuses, no other lets through, and a change of a user acts at once everywhere.

- OPC UA `Download` with `--trusted-keys`: an unsigned program is refused before it is
  compiled (it was taken as an online change); a program alice signed is taken.
- A removed or demoted user's open OPC UA session loses its rights at its next request.
- `softplc users passwd`: the old password over HTTP Basic (cached) and a page session opened
  with it stop working at their next request.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import Client, ua

from softplc.opcua.ids import string_id
from softplc.security import signing
from softplc.security.audit import AuditTrail
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.api.helpers import call
from tests.opcua.conftest import (  # noqa: F401 - transport_plc is a pytest fixture
    Plc,
    patient_client,
    start_plc,
    stop_plc,
    transport_plc,
)
from tests.support import free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
NS_URI = "urn:softplc"
DRILLING = (ROOT / "programs" / "drilling.yaml").read_text(encoding="utf-8")


def _client(plc: Plc, user: str, password: str) -> Client:
    client = patient_client(plc.url)
    client.set_user(user)
    client.set_password(password)
    return client


async def _program(client: Client) -> tuple[int, ua.NodeId]:
    ns = await client.get_namespace_index(NS_URI)
    return ns, string_id("PLC.Program", ns)


async def _call(client: Client, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    ns, program = await _program(client)
    request = ua.CallMethodRequest(ObjectId=program, InputArguments=list(args),
                                   MethodId=string_id(f"PLC.Program.{method}", ns))
    results: list[ua.CallMethodResult] = await client.uaclient.call([request])
    return results[0]


def _text(value: str) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.String)


def _download_args(signature: str = "") -> list[ua.Variant]:
    return [_text(DRILLING), ua.Variant(True, ua.VariantType.Boolean), _text("drilling.yaml"),
            _text(signature)]


@pytest.fixture
def signed_plc(tmp_path: Path, keys: Path) -> Iterator[Plc]:
    """transport.yaml RUNNING with `--trusted-keys` naming a directory that trusts alice."""
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    (trusted / "alice.pub").write_bytes((keys / "alice.pub").read_bytes())
    state = tmp_path / "state"
    state.mkdir()
    plc = start_plc("programs/transport.yaml", state, "--trusted-keys", str(trusted))
    try:
        yield plc
    finally:
        stop_plc(plc.proc)


def test_opcua_download_needs_a_trusted_signature_as_http_does(signed_plc: Plc,
                                                                 keys: Path) -> None:
    async def body() -> None:
        async with _client(signed_plc, "owner", signed_plc.token) as client:
            unsigned = await _call(client, "Download", *_download_args()[:3])
            assert unsigned.StatusCode.value == ua.StatusCodes.BadSecurityChecksFailed
            message = unsigned.OutputArguments[0].Value
            assert message == "download refused: not signed by a trusted key (trusted: alice)"
            by_mallory = signing.sign(DRILLING.encode(),
                                      signing.load_private(keys / "mallory.key"))
            wrong = await _call(client, "Download", *_download_args(by_mallory))
            assert wrong.StatusCode.value == ua.StatusCodes.BadSecurityChecksFailed
            by_alice = signing.sign(DRILLING.encode(), signing.load_private(keys / "alice.key"))
            taken = await _call(client, "Download", *_download_args(by_alice))
            assert taken.StatusCode.is_good(), taken.OutputArguments[0].Value
            assert "signed by alice" in taken.OutputArguments[0].Value
            assert taken.OutputArguments[1].Value == "RUNNING"

    asyncio.run(body())
    trail = [r for r in AuditTrail(signed_plc.state_dir).records()
             if r.get("action") == "Download"]
    assert [r["outcome"] for r in trail] == ["refused", "refused", "applied"]
    assert "not signed by a trusted key" in trail[0]["detail"]["message"]


def test_a_trusted_key_replaced_in_place_or_removed_acts_at_the_next_download(
        signed_plc: Plc, keys: Path) -> None:
    """`softplc keys trust` over a key of the same name, the directory's mtime as it was: the
    new key is trusted and the old one not, at once (it took a restart); the directory
    emptied: every download refused, not every one taken (it let unsigned ones through)."""
    trusted = signed_plc.state_dir.parent / "trusted"
    by = {name: signing.sign(DRILLING.encode(), signing.load_private(keys / f"{name}.key"))
          for name in ("alice", "mallory")}

    async def body() -> None:
        async with _client(signed_plc, "owner", signed_plc.token) as client:
            info = trusted.stat()
            (trusted / "alice.pub").write_bytes((keys / "mallory.pub").read_bytes())
            os.utime(trusted, ns=(info.st_atime_ns, info.st_mtime_ns))
            old = await _call(client, "Download", *_download_args(by["alice"]))
            assert old.StatusCode.value == ua.StatusCodes.BadSecurityChecksFailed
            new = await _call(client, "Download", *_download_args(by["mallory"]))
            assert new.StatusCode.is_good(), new.OutputArguments[0].Value
            (trusted / "alice.pub").unlink()
            emptied = await _call(client, "Download", *_download_args()[:3])
            assert emptied.StatusCode.value == ua.StatusCodes.BadSecurityChecksFailed
            assert "no trusted key can be read" in emptied.OutputArguments[0].Value

    asyncio.run(body())


def test_a_removed_or_demoted_users_open_opcua_session_loses_its_rights(
        tmp_path: Path) -> None:
    state = tmp_path / "state"
    store = UserStore(state)
    store.add("op", Role.OPERATOR, "operator-password")
    store.add("eng", Role.ENGINEER, "engineer-password")
    plc = start_plc("programs/transport.yaml", state)

    async def body() -> None:
        async with _client(plc, "op", "operator-password") as op, \
                _client(plc, "eng", "engineer-password") as eng:
            assert (await _call(op, "Suspend")).StatusCode.is_good()
            assert (await _call(op, "Resume")).StatusCode.is_good()
            store.remove("op")  # `softplc users remove op` while its session is open
            refused = await _call(op, "Suspend")
            assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "the user was removed" in refused.OutputArguments[0].Value
            ns, _ = await _program(op)
            suspend = op.get_node(string_id("PLC.Program.Suspend", ns))
            executable = await suspend.read_attribute(ua.AttributeIds.UserExecutable)
            assert executable.Value is not None and executable.Value.Value is False
            assert (await _call(eng, "Halt")).StatusCode.is_good()
            store.set_role("eng", Role.OPERATOR)  # demoted: Reset needs engineer
            demoted = await _call(eng, "Reset")
            assert demoted.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "needs the engineer role (this session: operator)" in \
                demoted.OutputArguments[0].Value

    try:
        asyncio.run(body())
    finally:
        stop_plc(plc.proc)


def test_a_password_sent_in_clear_on_the_none_endpoint_is_refused(transport_plc: Plc) -> None:  # noqa: F811
    """The token policy names Basic256Sha256: a client that ignores it and sends the owner's
    key in clear over security None is refused, as the policy says (it was accepted)."""
    async def body() -> None:
        client = _client(transport_plc, "owner", transport_plc.token)
        own = client.server_policy

        def clear(token_type: ua.UserTokenType) -> ua.UserTokenPolicy:
            policy = own(token_type)
            return ua.UserTokenPolicy(PolicyId=policy.PolicyId, TokenType=policy.TokenType)

        client.server_policy = clear  # type: ignore[method-assign]
        with pytest.raises(ua.UaStatusCodeError) as caught:
            async with client:
                pass
        assert caught.value.code == ua.StatusCodes.BadIdentityTokenRejected
        async with _client(transport_plc, "owner", transport_plc.token) as good:
            assert (await _call(good, "Suspend")).StatusCode.is_good()  # encrypted: taken

    asyncio.run(body())
    failed = [r for r in AuditTrail(transport_plc.state_dir).records()
              if r.get("action") == "login" and r.get("iface") == "opcua"]
    assert failed and "unencrypted" in failed[-1]["detail"]["reason"]


def _basic(name: str, password: str) -> dict[str, str]:
    return {"Authorization": "Basic " + base64.b64encode(f"{name}:{password}".encode()).decode()}


def test_a_changed_password_acts_at_once_over_basic_and_sessions(tmp_path: Path) -> None:
    where = tmp_path
    UserStore(where / "state").add("op", Role.OPERATOR, "old-password-1")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--api",
                      f"127.0.0.1:{port}", "--modbus", "off", "--opcua", "off", "--state-dir",
                      "state", "--quiet", "--period", "10ms"],
                     lambda: call(url, "GET", "/api/v1/status", timeout_s=5).status == 200,
                     cwd=where, stdout=subprocess.DEVNULL, what="softplc run answering"):
        old = _basic("op", "old-password-1")
        assert call(url, "POST", "/api/v1/stop", headers=old).status == 200  # verified, cached
        login = call(url, "POST", "/api/v1/login",
                     body=json.dumps({"user": "op", "password": "old-password-1"}))
        assert login.status == 200
        cookie = {"Cookie": login.headers["Set-Cookie"].split(";")[0]}
        assert call(url, "POST", "/api/v1/resume", headers=cookie).status == 200
        changed = subprocess.run(
            [sys.executable, "-m", "softplc.cli", "users", "passwd", "op", "--state-dir",
             "state"], cwd=where, input="new-password-1\n", capture_output=True, text=True,
            timeout=120, check=False)
        assert changed.returncode == 0, changed.stderr
        assert call(url, "POST", "/api/v1/stop", headers=old).status == 401
        assert call(url, "POST", "/api/v1/stop", headers=cookie).status == 401
        assert call(url, "GET", "/api/v1/status").body["state"] == "RUNNING"
        new = call(url, "POST", "/api/v1/stop", headers=_basic("op", "new-password-1"))
        assert new.status == 200
