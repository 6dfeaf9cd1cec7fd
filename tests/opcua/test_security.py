"""OPC UA security against a real `softplc run` on loopback (issue 31): a SignAndEncrypt
client with an untrusted certificate is refused and its certificate kept; after `softplc
trust accept` it connects; an operator's Suspend works, a viewer's is refused and both are
told so (UserExecutable); anonymous sessions read UserAccessLevel without the write bits and
their writes are refused; every call, write and failed login is in the audit trail."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import (
    SecurityPolicyAes128Sha256RsaOaep,
    SecurityPolicyAes256Sha256RsaPss,
    SecurityPolicyBasic256Sha256,
)

from softplc.opcua.ids import string_id
from softplc.security.audit import AuditTrail
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.opcua.certs import client_certificate
from tests.opcua.conftest import ROOT, Plc, patient_client

NS_URI = "urn:softplc"
CLIENT_URI = "urn:softplc-test:client"
PASSWORDS = {"op": "operator-password", "view": "viewer-password"}
WRITE_BITS = 1 << ua.AccessLevel.CurrentWrite


def _users(plc: Plc) -> None:
    store = UserStore(plc.state_dir)
    store.add("op", Role.OPERATOR, PASSWORDS["op"])
    store.add("view", Role.VIEWER, PASSWORDS["view"])


async def _secure(plc: Plc, cert: Path, key: Path, user: str | None = None,
                  policy: type = SecurityPolicyBasic256Sha256,
                  mode: ua.MessageSecurityMode = ua.MessageSecurityMode.SignAndEncrypt,
                  password: str | None = None) -> Client:
    client = patient_client(plc.url)
    client.application_uri = CLIENT_URI
    await client.set_security(policy, str(cert), str(key), mode=mode)
    if user is not None:
        client.set_user(user)
        client.set_password(password or PASSWORDS[user])
    return client


def _softplc(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=60, check=False)


async def _program(client: Client) -> tuple[int, ua.NodeId]:
    ns = await client.get_namespace_index(NS_URI)
    return ns, string_id("PLC.Program", ns)


async def _call(client: Client, method: str) -> ua.CallMethodResult:
    ns, program = await _program(client)
    request = ua.CallMethodRequest(ObjectId=program,
                                   MethodId=string_id(f"PLC.Program.{method}", ns))
    results: list[ua.CallMethodResult] = await client.uaclient.call([request])
    return results[0]


async def _user_executable(client: Client, method: str) -> bool:
    ns, _ = await _program(client)
    node = client.get_node(string_id(f"PLC.Program.{method}", ns))
    value = await node.read_attribute(ua.AttributeIds.UserExecutable)
    assert value.Value is not None
    return bool(value.Value.Value)


def test_untrusted_refused_then_accepted_roles_and_audit(transport_plc: Plc,
                                                         tmp_path: Path) -> None:
    plc = transport_plc
    _users(plc)
    cert, key = client_certificate(tmp_path, "softplc-test-client", CLIENT_URI)
    rejected = plc.state_dir / "pki" / "rejected"

    async def scenario() -> None:
        with pytest.raises(ua.UaStatusCodeError) as refused:  # at OpenSecureChannel
            async with await _secure(plc, cert, key, "op"):
                pass
        assert refused.value.code == ua.StatusCodes.BadSecurityChecksFailed
        kept = list(rejected.glob("*.der"))
        assert [p.read_bytes() for p in kept] == [cert.read_bytes()]

        listed = _softplc("trust", "list", "--state-dir", str(plc.state_dir))
        assert kept[0].stem in listed.stdout and "rejected" in listed.stdout
        accepted = _softplc("trust", "accept", kept[0].stem, "--state-dir", str(plc.state_dir))
        assert accepted.returncode == 0, accepted.stderr
        assert not list(rejected.glob("*.der"))

        async with await _secure(plc, cert, key, "op") as operator:
            assert await _user_executable(operator, "Suspend")  # Running: Suspend works
            assert not await _user_executable(operator, "Reset")  # Reset needs an engineer
            assert (await _call(operator, "Suspend")).StatusCode.is_good()
            ns, _ = await _program(operator)
            state = operator.get_node(string_id("PLC.Status.State", ns))
            for _ in range(200):
                if await state.read_value() == "STOPPED":
                    break
                await asyncio.sleep(0.05)
            assert await state.read_value() == "STOPPED"
            assert (await _call(operator, "Resume")).StatusCode.is_good()

        async with await _secure(plc, cert, key, "view", SecurityPolicyAes256Sha256RsaPss,
                                 ua.MessageSecurityMode.Sign) as viewer:
            assert not await _user_executable(viewer, "Suspend")
            result = await _call(viewer, "Suspend")
            assert result.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
            assert "operator" in result.OutputArguments[0].Value

        with pytest.raises(ua.UaStatusCodeError) as wrong:
            async with await _secure(plc, cert, key, "op", SecurityPolicyAes128Sha256RsaOaep,
                                     password="not-the-password"):
                pass
        assert wrong.value.code == ua.StatusCodes.BadUserAccessDenied

        async with patient_client(plc.url) as anonymous:  # security None: loopback
            ns, _ = await _program(anonymous)
            hold = anonymous.get_node(string_id("PLC.Symbols.hold", ns))
            level = await hold.read_attribute(ua.AttributeIds.UserAccessLevel)
            own = await hold.read_attribute(ua.AttributeIds.AccessLevel)
            assert level.Value is not None and own.Value is not None
            assert not level.Value.Value & WRITE_BITS
            assert own.Value.Value & WRITE_BITS  # the node is writable: the session may not
            with pytest.raises(ua.UaStatusCodeError) as denied:
                await hold.write_value(ua.Variant(True, ua.VariantType.Boolean))
            assert denied.value.code == ua.StatusCodes.BadUserAccessDenied
            assert not await _user_executable(anonymous, "Suspend")

    asyncio.run(asyncio.wait_for(scenario(), 120))
    records = [r for r in AuditTrail(plc.state_dir).records() if r.get("iface") == "opcua"]
    seen = {(r["user"], r["action"], r["outcome"]) for r in records}
    assert {("op", "Suspend", "applied"), ("op", "Resume", "applied"),
            ("view", "Suspend", "denied"), ("op", "login", "failed"),
            (None, "write", "denied"), (None, "secure channel", "failed")} <= seen, seen
    suspend = next(r for r in records if r["action"] == "Suspend" and r["user"] == "op")
    assert suspend["role"] == "operator" and suspend["peer"] == "127.0.0.1"
    assert _softplc("audit", "--verify", "--state-dir", str(plc.state_dir)).returncode == 0
    assert any(r.get("iface") == "cli" and r["action"].startswith("trust accept")
               for r in AuditTrail(plc.state_dir).records())
