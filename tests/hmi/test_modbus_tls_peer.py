"""Modbus/TCP Security without sockets: the role of a client certificate (hmi/tlspeer.py),
the certificate a TLS Certificate message offers, what a write is recorded as, and the
audit recorder's bounds (hmi/tlsaudit.py)."""

from __future__ import annotations

import asyncio
import struct
from pathlib import Path
from typing import Any

import pytest

from softplc.hmi.tlsaudit import AuditRecorder
from softplc.hmi.tlspeer import (
    NO_ROLE,
    ROLES,
    der_string,
    describe_write,
    identity_of,
    offered_certificate,
)
from softplc.security.roles import Act, Role, needs
from tests.hmi.test_modbus_tls import make_client, utf8_string


def test_the_role_names_are_softplcs() -> None:
    assert [role.label for role in sorted(Role)] == list(ROLES)
    assert (needs(Act.WRITE), Role.VIEWER.label) == (Role.OPERATOR, NO_ROLE)


@pytest.mark.parametrize(("role", "granted", "writes"), [
    ("operator", "operator", True), (" Engineer ", "engineer", True), ("ADMIN", "admin", True),
    ("viewer", "viewer", False), ("supervisor", "viewer", False), ("", "viewer", False),
    (None, "viewer", False)])
def test_a_certificates_role_decides_whether_it_writes(
        tmp_path: Path, role: str | None, granted: str, writes: bool) -> None:
    identity = identity_of(make_client(tmp_path, "panel-7", role).der)
    assert (identity.user, identity.role, identity.may_write) == ("panel-7", granted, writes)
    assert identity.certificate_role == role
    assert identity.audit() == {"user": "panel-7", "role": granted, "via": "certificate"}


def test_a_role_that_is_no_string_grants_nothing(tmp_path: Path) -> None:
    integer = bytes([0x02, 0x01, 0x05])  # an ASN.1 INTEGER where the string belongs
    identity = identity_of(make_client(tmp_path, "odd", None, role_der=integer).der)
    assert (identity.role, identity.certificate_role, identity.may_write) == (
        "viewer", None, False)


def test_der_strings() -> None:
    assert der_string(utf8_string("operator")) == "operator"
    assert der_string(bytes([0x13, 3]) + b"adm") == "adm"  # PrintableString
    long = "x" * 200
    assert der_string(bytes([0x0C, 0x81, 200]) + long.encode()) == long
    assert der_string(bytes([0x0C, 5]) + b"abc") is None  # shorter than its length
    assert der_string(bytes([0x0C, 2]) + b"\xff\xfe") is None  # not UTF-8
    assert der_string(b"") is None


def _certificate_message(version: int, certificates: list[bytes]) -> bytes:
    entries = b"".join(len(c).to_bytes(3, "big") + c + (b"\x00\x00" if version >= 0x0304
                                                        else b"") for c in certificates)
    body = (b"\x00" if version >= 0x0304 else b"") + len(entries).to_bytes(3, "big") + entries
    return bytes([11]) + len(body).to_bytes(3, "big") + body


@pytest.mark.parametrize("version", [0x0303, 0x0304])
def test_the_offered_certificate_is_the_first_of_the_message(version: int) -> None:
    leaf, issuer = b"\x30\x03leaf", b"\x30\x05issuer"
    assert offered_certificate(version, _certificate_message(version, [leaf, issuer])) == leaf
    assert offered_certificate(version, _certificate_message(version, [])) is None
    assert offered_certificate(version, _certificate_message(version, [leaf])[:-4]) is None
    assert offered_certificate(version, b"\x0b\x00") is None


def test_writes_are_described_for_the_trail() -> None:
    assert describe_write(struct.pack(">BHH", 5, 9, 0xFF00)) == {
        "function": 5, "table": "coils", "address": 9, "values": [1]}
    assert describe_write(struct.pack(">BHH", 6, 3, 1234))["values"] == [1234]
    assert describe_write(struct.pack(">BHHBB", 15, 0, 3, 1, 0b101))["values"] == [1, 0, 1]
    assert describe_write(struct.pack(">BHHBHH", 16, 7, 2, 4, 1, 2)) == {
        "function": 16, "table": "holding registers", "address": 7, "values": [1, 2]}
    assert describe_write(struct.pack(">BHHHHBH", 23, 0, 1, 40, 1, 2, 99)) == {
        "function": 23, "table": "holding registers", "address": 40, "values": [99]}
    assert describe_write(bytes([16, 0])) == {"function": 16, "malformed": True}


class _Trail:
    def __init__(self) -> None:
        self.entries: list[dict[str, Any]] = []

    def append(self, entry: dict[str, Any]) -> object:
        self.entries.append(entry)
        return entry


class _Trust:
    def __init__(self) -> None:
        self.rejected: list[bytes] = []

    def trusted(self) -> frozenset[bytes]:
        return frozenset()

    def reject(self, der: bytes) -> str | None:
        self.rejected.append(der)
        return "kept"


def test_refusals_are_recorded_once_per_interval_and_peer_with_a_count(tmp_path: Path) -> None:
    trail, trust = _Trail(), _Trust()
    der = make_client(tmp_path, "flood", "operator").der

    async def refuse() -> None:
        recorder = AuditRecorder(trail, trust, refusal_interval_s=10.0)
        for now_s in (0.0, 1.0, 2.0, 11.0):
            recorder.refused("10.0.0.9", "untrusted-certificate", "bad", der, now_s)
        recorder.refused("10.0.0.8", "no-certificate", "none", None, 2.0)
        await recorder.close()

    asyncio.run(refuse())
    assert [(e["peer"], e["user"], e["detail"]["not_recorded_before"]) for e in trail.entries] \
        == [("10.0.0.9", "flood", 0), ("10.0.0.9", "flood", 2), ("10.0.0.8", None, 0)]
    assert trail.entries[0]["detail"]["kept_as"] == "kept"
    assert trust.rejected == [der] * 4  # kept every time (trust.py keeps one copy)
