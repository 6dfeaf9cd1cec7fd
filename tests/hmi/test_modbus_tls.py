"""Modbus/TCP Security (hmi/secure.py) with real clients: pymodbus' TLS client, raw TLS
sockets, openssl s_client. Certificates are made here: the PLC's as the wiring makes it
(security/tls.py in STATE_DIR/modbus-tls), clients' with or without the ModbusRole extension."""

from __future__ import annotations

import datetime
import shutil
import socket
import ssl
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from pymodbus.client import ModbusTlsClient
from pymodbus.exceptions import ModbusException

from softplc.core.image import ImageSizes, parse_address
from softplc.hmi.secure import MODBUS_TLS_DIR, SecureModbusSlave, TlsConfig
from softplc.hmi.tlspeer import ROLE_OID
from softplc.security.audit import AuditTrail
from softplc.security.tls import TlsSettings, certificate
from softplc.security.trust import TrustList, name_of
from tests.hmi.helpers import ImageSource, SlaveThread, adu, run_in_thread

OPENSSL = shutil.which("openssl")


@dataclass(frozen=True)
class Client:
    cert: Path
    key: Path
    der: bytes


def utf8_string(text: str) -> bytes:
    data = text.encode()
    assert len(data) < 128
    return bytes([0x0C, len(data)]) + data


def make_client(directory: Path, common_name: str, role: str | None,
                role_der: bytes | None = None) -> Client:
    """A self-signed client certificate (ECDSA P-256) with `role` in a ModbusRole extension
    (None: no extension; `role_der` gives the extension's bytes as they are)."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = datetime.datetime.now(datetime.UTC)
    builder = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(days=1))
               .not_valid_after(now + datetime.timedelta(days=30))
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]),
                              critical=False))
    if role is not None or role_der is not None:
        value = role_der if role_der is not None else utf8_string(role or "")
        builder = builder.add_extension(x509.UnrecognizedExtension(ROLE_OID, value),
                                        critical=False)
    cert = builder.sign(key, hashes.SHA256())
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / f"{common_name}.pem", directory / f"{common_name}.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return Client(cert_path, key_path, cert.public_bytes(serialization.Encoding.DER))


def client_context(server_cert: Path, client: Client | None,
                   maximum: ssl.TLSVersion | None = None) -> ssl.SSLContext:
    """Verifies the PLC by its certificate (a pin: no host name), presents `client`'s."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.load_verify_locations(server_cert)
    if client is not None:
        context.load_cert_chain(client.cert, client.key)
    if maximum is not None:
        context.maximum_version = maximum
    return context


@dataclass
class Plc:
    state: Path
    server_cert: Path
    trust: TrustList
    source: ImageSource
    thread: SlaveThread

    @property
    def port(self) -> int:
        return self.thread.port

    def records(self, action: str | None = None) -> list[dict[str, Any]]:
        """The Modbus records of the trail (call after `thread.stop()`: all are written)."""
        return [r for r in AuditTrail(self.state).records()
                if r.get("iface") == "modbus" and action in (None, r.get("action"))]


@contextmanager
def secure_plc(state: Path, source: ImageSource, **options: Any) -> Iterator[Plc]:
    """A SecureModbusSlave on 127.0.0.1, a free port, over `state` (refusals all recorded)."""
    cert, key, _ = certificate(TlsSettings(), state / MODBUS_TLS_DIR, "127.0.0.1")
    trust = TrustList(state, MODBUS_TLS_DIR)
    config = TlsConfig(cert, key, trust, AuditTrail(state), refusal_interval_s=0.0)
    slave = SecureModbusSlave(source, source.sink, tls=config, sizes=source.image.sizes,
                              port=0, **options)
    with run_in_thread(slave, start_timeout_s=30.0) as thread:
        yield Plc(state, cert, trust, source, thread)


# -- over the network: pymodbus' TLS client, raw TLS sockets, openssl -------------------------

ROLE_USERS = {"operator": "hmi-op", "viewer": "hmi-view", None: "hmi-norole",
              "supervisor": "hmi-unknown"}


@pytest.fixture
def source() -> ImageSource:
    src = ImageSource(ImageSizes())
    src.image.qx[[0, 3]] = True
    src.image.qw[:4] = [10, 11, 12, 13]
    src.publish()
    return src


def trusted_client(plc: Plc, tmp_path: Path, role: str | None) -> Client:
    client = make_client(tmp_path / "clients", ROLE_USERS[role], role)
    plc.trust.accept(str(client.cert))
    return client


def tls_client(plc: Plc, client: Client | None) -> ModbusTlsClient:
    return ModbusTlsClient("127.0.0.1", port=plc.port, timeout=5, retries=0,
                           sslctx=client_context(plc.server_cert, client))


def handshake(plc: Plc, client: Client | None, maximum: ssl.TLSVersion) -> bytes:
    """A raw TLS connection's handshake, then one FC1 request: the reply's bytes."""
    context = client_context(plc.server_cert, client, maximum)
    with socket.create_connection(("127.0.0.1", plc.port), timeout=10) as raw, \
            context.wrap_socket(raw) as sock:
        sock.sendall(adu(bytes([1, 0, 0, 0, 8])))
        return sock.recv(64)


def test_an_operator_certificate_writes_and_the_write_is_audited(
        tmp_path: Path, source: ImageSource) -> None:
    with secure_plc(tmp_path / "state", source) as plc:
        client = tls_client(plc, trusted_client(plc, tmp_path, "operator"))
        assert client.connect()
        try:
            written = client.write_coil(5, True, device_id=1)
            assert not written.isError(), written
            registers = client.write_registers(1, [7, 8], device_id=1)
            assert not registers.isError(), registers
            read = client.read_coils(0, count=8, device_id=1)
            assert read.bits[:8] == [True, False, False, True] + [False] * 4
        finally:
            client.close()
    assert [(w.address, w.values) for w in source.writes] == [
        (parse_address("%QX0.5"), (1,)), (parse_address("%QW1"), (7, 8))]
    records = plc.records("write")
    assert [(r["user"], r["role"], r["outcome"], r["status"]) for r in records] == [
        ("hmi-op", "operator", "applied", 0)] * 2
    assert records[0]["detail"] == {"function": 5, "table": "coils", "address": 5,
                                    "values": [1], "unit": 1, "certificate_role": "operator"}
    assert records[1]["detail"]["values"] == [7, 8] and records[1]["peer"] == "127.0.0.1"
    assert AuditTrail(plc.state).verify().ok


@pytest.mark.parametrize("role", ["viewer", None, "supervisor"])
def test_a_certificate_without_a_writing_role_reads_and_gets_01_for_writes(
        tmp_path: Path, source: ImageSource, role: str | None) -> None:
    with secure_plc(tmp_path / "state", source) as plc:
        client = tls_client(plc, trusted_client(plc, tmp_path, role))
        assert client.connect()
        try:
            refused = client.write_coil(5, True, device_id=1)
            assert refused.isError() and refused.exception_code == 1, refused
            registers = client.write_registers(1, [7], device_id=1)
            assert registers.isError() and registers.exception_code == 1, registers
            read = client.read_holding_registers(0, count=4, device_id=1)
            assert not read.isError() and read.registers == [10, 11, 12, 13]
        finally:
            client.close()
    assert source.writes == []
    records = plc.records("write")
    assert [(r["user"], r["role"], r["outcome"], r["status"]) for r in records] == [
        (ROLE_USERS[role], "viewer", "denied", 1)] * 2
    assert records[0]["detail"]["certificate_role"] == role


def test_a_client_without_a_certificate_is_refused_at_the_handshake(
        tmp_path: Path, source: ImageSource) -> None:
    with secure_plc(tmp_path / "state", source) as plc:
        with pytest.raises(ssl.SSLError):  # TLS 1.2: the handshake itself fails
            handshake(plc, None, ssl.TLSVersion.TLSv1_2)
        # TLS 1.3: the client's side of the handshake ends before the server has checked it,
        # so the refusal is the alert that answers its first request.
        with pytest.raises((ssl.SSLError, ConnectionError)):
            reply = handshake(plc, None, ssl.TLSVersion.TLSv1_3)
            assert reply == b"", reply
            raise ConnectionError("closed")
        client = tls_client(plc, None)
        try:
            answered = client.connect() and not client.read_coils(0, count=1).isError()
        except ModbusException:
            answered = False
        finally:
            client.close()
        assert not answered
    assert {r["status"] for r in plc.records("connect")} == {"no-certificate"}
    assert all(r["outcome"] == "denied" and r["user"] is None
               for r in plc.records("connect"))
    assert plc.trust.certificates() == []


def test_an_untrusted_certificate_is_refused_kept_and_serves_once_accepted(
        tmp_path: Path, source: ImageSource) -> None:
    stranger = make_client(tmp_path / "clients", "stranger", "operator")
    with secure_plc(tmp_path / "state", source) as plc:
        with pytest.raises(ssl.SSLError):
            handshake(plc, stranger, ssl.TLSVersion.TLSv1_2)
        with pytest.raises((ssl.SSLError, ConnectionError)):
            assert handshake(plc, stranger, ssl.TLSVersion.TLSv1_3) == b""
            raise ConnectionError("closed")
        deadline = time.monotonic() + 20
        while not plc.trust.certificates() and time.monotonic() < deadline:
            time.sleep(0.05)  # kept by the audit thread, after the refusal
        [kept] = plc.trust.certificates()
        assert kept.state == "rejected" and kept.name == name_of(stranger.der)
        assert source.writes == []
        plc.trust.accept(kept.name)  # what `softplc trust accept` does for OPC UA
        client = tls_client(plc, stranger)
        assert client.connect()
        try:
            assert not client.write_coil(2, True, device_id=1).isError()
        finally:
            client.close()
    assert [w.address for w in source.writes] == [parse_address("%QX0.2")]
    refused = plc.records("connect")
    assert {(r["user"], r["status"]) for r in refused} == {("stranger", "untrusted-certificate")}
    assert refused[0]["detail"]["kept_as"] == kept.name
    assert [(r["user"], r["role"]) for r in plc.records("write")] == [("stranger", "operator")]


@pytest.mark.skipif(OPENSSL is None, reason="Debian's openssl is not installed")
def test_openssl_s_client_gets_tls_1_2_with_a_certificate_and_never_1_1(
        tmp_path: Path, source: ImageSource) -> None:
    assert OPENSSL is not None
    with secure_plc(tmp_path / "state", source) as plc:
        client = trusted_client(plc, tmp_path, "operator")

        def s_client(*flags: str) -> subprocess.CompletedProcess[str]:
            return subprocess.run([OPENSSL, "s_client", "-connect", f"127.0.0.1:{plc.port}",
                                   "-CAfile", str(plc.server_cert), *flags], input="",
                                  capture_output=True, text=True, timeout=60)

        # SECLEVEL=0: this client offers TLS 1.1 itself; the server must be the one to refuse.
        old = s_client("-tls1_1", "-cipher", "DEFAULT:@SECLEVEL=0",
                       "-cert", str(client.cert), "-key", str(client.key))
        assert old.returncode != 0 and "Cipher is (NONE)" in old.stdout, old.stdout
        new = s_client("-tls1_2", "-cert", str(client.cert), "-key", str(client.key))
        assert new.returncode == 0, new.stdout + new.stderr
        assert "Protocol  : TLSv1.2" in new.stdout and "Verify return code: 0 (ok)" in new.stdout
    assert "tls" in {r["status"] for r in plc.records("connect")}


def test_the_connection_caps_hold_before_the_handshake(
        tmp_path: Path, source: ImageSource) -> None:
    with secure_plc(tmp_path / "state", source, max_per_peer=1) as plc:
        client = tls_client(plc, trusted_client(plc, tmp_path, "operator"))
        with socket.create_connection(("127.0.0.1", plc.port), timeout=10) as idle:
            deadline = time.monotonic() + 20  # the silent one holds the slot
            while plc.thread.slave.connection_count < 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert client.connect()  # it takes the slot: the silent one never was live
            try:
                assert not client.read_coils(0, count=1, device_id=1).isError()
            finally:
                client.close()
            idle.settimeout(10)
            assert idle.recv(1) == b""
        stats = plc.thread.slave.connection_stats
        assert (stats.admitted, stats.evicted) == (2, 1)
