"""The trust list and the server's certificate, in-process (no socket): names, accept and
remove, the bounded rejected/ folder, chains, file modes, and which endpoints and identity
tokens a loopback and a non-loopback bind offer (issue 31)."""

from __future__ import annotations

import asyncio
import stat
from pathlib import Path

import pytest
from asyncua import ua
from cryptography import x509

from softplc.opcua.limits import OpcUaLimits
from softplc.opcua.secure import SECURE_POLICIES, Security, application_uri
from softplc.security import trust as trustmod
from softplc.security.trust import TrustError, TrustList, first_certificate
from tests.opcua.certs import client_certificate


def test_reject_accept_remove(tmp_path: Path) -> None:
    cert, _ = client_certificate(tmp_path, "station-7", "urn:test:station-7")
    der = cert.read_bytes()
    trust = TrustList(tmp_path / "state")
    assert not trust.is_trusted(der)
    name = trust.reject(der)
    assert name is not None and name.startswith("station-7_")
    assert trust.reject(der) is None  # kept once: a retry is not a new certificate
    [entry] = trust.certificates()
    assert (entry.state, entry.uri) == ("rejected", "urn:test:station-7")
    accepted = trust.accept(name[:12])  # a unique start of the name will do
    assert accepted.state == "trusted" and trust.is_trusted(der)
    assert not (trust.rejected_dir / f"{name}.der").exists()
    for path in (trust.dir, trust.trusted_dir, trust.rejected_dir):
        assert stat.S_IMODE(path.stat().st_mode) == 0o700
    assert stat.S_IMODE((trust.trusted_dir / f"{name}.der").stat().st_mode) == 0o600
    trust.remove(name)
    assert not trust.is_trusted(der)
    with pytest.raises(TrustError):
        trust.remove(name)


def test_accept_a_file_and_a_chain(tmp_path: Path) -> None:
    cert, _ = client_certificate(tmp_path, "scada", "urn:test:scada")
    other, _ = client_certificate(tmp_path, "ca-ish", "urn:test:other")
    trust = TrustList(tmp_path / "state")
    trust.accept(str(cert))
    chain = cert.read_bytes() + other.read_bytes()
    assert first_certificate(chain) == cert.read_bytes()
    assert trust.is_trusted(first_certificate(chain))
    assert not trust.is_trusted(other.read_bytes())


def test_rejected_is_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(trustmod, "MAX_REJECTED", 3)
    trust = TrustList(tmp_path / "state")
    for n in range(5):
        cert, _ = client_certificate(tmp_path, f"c{n}", f"urn:test:c{n}")
        trust.reject(cert.read_bytes())
    assert len(list(trust.rejected_dir.glob("*.der"))) == 3
    assert trust.reject(b"\x30\x03junk") is None  # not a certificate: nothing kept


@pytest.mark.parametrize(("host", "loopback"), [("127.0.0.1", True), ("0.0.0.0", False)])
def test_endpoints_and_certificate(tmp_path: Path, host: str, loopback: bool) -> None:
    async def endpoints() -> list[ua.EndpointDescription]:
        security = Security(tmp_path, host, 4855)
        await security.prepare()
        server = security.server(OpcUaLimits())
        await server.init()
        server.set_endpoint(f"opc.tcp://{host}:4855")
        await server.set_application_uri(application_uri(4855))
        await security.apply(server)
        await server._setup_server_nodes()
        return await server.get_endpoints()

    found = asyncio.run(asyncio.wait_for(endpoints(), 60))
    offered = {(e.SecurityPolicyUri.rpartition("#")[2], e.SecurityMode) for e in found}
    secure = {(p.name.rpartition("_")[0].replace("Aes128Sha256RsaOaep", "Aes128_Sha256_RsaOaep")
               .replace("Aes256Sha256RsaPss", "Aes256_Sha256_RsaPss"),
               ua.MessageSecurityMode[p.name.rpartition("_")[2]]) for p in SECURE_POLICIES}
    none = {("None", ua.MessageSecurityMode.None_)}
    assert offered == (secure | none if loopback else secure)
    tokens = {t.TokenType for e in found for t in e.UserIdentityTokens}
    assert (ua.UserTokenType.Anonymous in tokens) is loopback
    for endpoint in found:  # a password never travels in clear: encrypted or signed-only
        for token in endpoint.UserIdentityTokens:
            if token.TokenType == ua.UserTokenType.UserName and \
                    endpoint.SecurityMode != ua.MessageSecurityMode.SignAndEncrypt:
                assert token.SecurityPolicyUri.endswith("Basic256Sha256") or \
                    token.SecurityPolicyUri == endpoint.SecurityPolicyUri
    own = tmp_path / "pki" / "own"
    assert stat.S_IMODE((own / "key.pem").stat().st_mode) == 0o600
    assert stat.S_IMODE(own.stat().st_mode) == 0o700
    cert = x509.load_der_x509_certificate((own / "cert.der").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [application_uri(4855)]
    assert found[0].ServerCertificate == (own / "cert.der").read_bytes()


def test_new_uri_new_certificate_same_key(tmp_path: Path) -> None:
    from softplc.opcua.pki import server_identity

    first = server_identity(tmp_path, "urn:softplc:h:4840", ["h"])
    again = server_identity(tmp_path, "urn:softplc:h:4840", ["h"])
    key = first.key.read_bytes()
    moved = server_identity(tmp_path, "urn:softplc:h:4841", ["h"])
    assert (first.made, again.made, moved.made) == (True, False, True)
    assert again.thumbprint == first.thumbprint != moved.thumbprint
    assert moved.key.read_bytes() == key
