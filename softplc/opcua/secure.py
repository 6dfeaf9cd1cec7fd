"""The OPC UA server's secure side (issue 31): endpoints, certificates, trust and logins.

Owns: which endpoints are offered (Basic256Sha256, Aes128_Sha256_RsaOaep and
Aes256_Sha256_RsaPss, each in Sign and SignAndEncrypt; None only on a loopback bind), which
identity tokens (anonymous only on a loopback bind; user name), the server's certificate
(pki.py), the check of a new secure channel's client certificate against the trust list
(security/trust.py: an untrusted one is refused and kept in STATE_DIR/pki/rejected/), the checks
of CreateSession (the certificate is the channel's, and names the client's ApplicationUri),
checking a user-name token's password before asyncua activates the session (access.py), and
the audit records of refused certificates and failed logins.
Does not know: the address space, symbols, the channel, the scan.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Awaitable, Callable, Coroutine
from pathlib import Path
from typing import Any, Final

from asyncua import ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto.security_policies import SecurityPolicyNone
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary
from cryptography import x509

from softplc.opcua.access import ClientServices, Login, PlcUser, Recorder, Users
from softplc.opcua.door import DoorServer
from softplc.opcua.ids import numeric_id
from softplc.opcua.pki import ServerIdentity, server_identity
from softplc.security import auth
from softplc.security.programgate import ProgramGate
from softplc.security.settings import load as load_settings
from softplc.security.trust import TrustList, first_certificate

log = logging.getLogger(__name__)

P = ua.SecurityPolicyType
SECURE_POLICIES: Final = (P.Basic256Sha256_SignAndEncrypt, P.Basic256Sha256_Sign,
                          P.Aes128Sha256RsaOaep_SignAndEncrypt, P.Aes128Sha256RsaOaep_Sign,
                          P.Aes256Sha256RsaPss_SignAndEncrypt, P.Aes256Sha256RsaPss_Sign)
# Part 4 / Part 6: a client whose certificate is not trusted learns no more than this
UNTRUSTED: Final = ua.StatusCodes.BadSecurityChecksFailed
_ACTIVATE: Final = numeric_id(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary)
_CREATE: Final = numeric_id(ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary)


def application_uri(port: int) -> str:
    """Per host and port: several softplcs may share a host."""
    return f"urn:softplc:{socket.gethostname()}:{port}"


class Security:
    """The secure side of one server on `host:port`."""

    def __init__(self, state_dir: Path, host: str, port: int) -> None:
        self.state_dir, self.host, self.port = Path(state_dir), host, port
        self.loopback = auth.is_loopback(host)
        self.trust = TrustList(state_dir)
        self.recorder = Recorder(state_dir)
        settings = load_settings(self.state_dir)  # what `softplc run` was started with
        self.programs = ProgramGate(self.state_dir, settings.trusted_dir(self.state_dir),
                                    required=settings.trusted_keys is not None)
        self.users: Users | None = None
        self.identity: ServerIdentity | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def prepare(self) -> None:
        """The owner's key and the server's certificate (made at the first start: RSA key
        generation takes a while, so in a thread)."""
        token = await asyncio.to_thread(auth.load_or_create_token, self.state_dir)
        self.users = Users(self.state_dir, token, self.loopback)
        hosts = [socket.gethostname()]
        if self.host.strip("[]") not in ("", "0.0.0.0", "::"):
            hosts.append(self.host.strip("[]"))
        self.identity = await asyncio.to_thread(server_identity, self.state_dir,
                                                application_uri(self.port), hosts)

    def server(self, limits: Any) -> DoorServer:
        assert self.users is not None
        return DoorServer(limits, channel_check=self.channel_check, guard=self.guard,
                          user_manager=self.users)

    async def apply(self, server: DoorServer) -> None:
        assert self.identity is not None
        await server.load_certificate(str(self.identity.cert))
        await server.load_private_key(str(self.identity.key))
        policies = ([P.NoSecurity] if self.loopback else []) + list(SECURE_POLICIES)
        server.set_security_policy(policies, ClientServices())
        server.set_identity_tokens(([ua.AnonymousIdentityToken] if self.loopback else [])
                                   + [ua.UserNameIdentityToken])

    async def stop(self) -> None:
        for task in list(self._tasks):
            with contextlib.suppress(Exception):
                await task

    # -- secure channels ----------------------------------------------------------------------

    def channel_check(self, peer: str, policy_uri: str, sent: bytes | None) -> int | None:
        """None (go on) or why a new secure channel is refused. Security None is only ever
        offered on loopback (asyncua refuses a policy it does not offer)."""
        if policy_uri == SecurityPolicyNone.URI:
            return None
        der = first_certificate(sent or b"")
        if der and self.trust.is_trusted(der):
            return None
        name = self.trust.reject(der) if der else None
        if name is not None:  # audited once: a certificate tried again is counted only
            log.warning("OPC UA client certificate %s from %s refused: not trusted (softplc "
                        "trust accept %s)", name, peer, name)
            self._background(self.recorder.record(
                {"via": "certificate", "peer": peer}, "secure channel", "failed", UNTRUSTED,
                {"certificate": name, "reason": "not in the trust list"}))
        return UNTRUSTED

    # -- requests: CreateSession and ActivateSession -------------------------------------------

    async def guard(self, peer: str, processor: UaProcessor, typeid: ua.NodeId, header: Any,
                    body: Buffer, dispatch: Callable[[], Awaitable[Any]]) -> Any:
        if typeid == _CREATE:
            _check_session_certificate(processor, body)
        elif typeid == _ACTIVATE:
            await self._login(peer, processor, header, body)
        answer = await dispatch()
        session = processor.session
        if typeid == _ACTIVATE and session is not None and isinstance(session.user, PlcUser):
            session.user.peer = peer
        return answer

    async def _login(self, peer: str, processor: UaProcessor, header: Any, body: Buffer) -> None:
        """A user-name token's password is checked here (scrypt, in a thread); asyncua's
        synchronous user manager then finds the verified pair (access.Users)."""
        assert self.users is not None
        params = struct_from_binary(ua.ActivateSessionParameters, body.copy())
        token = params.UserIdentityToken
        session = processor.session or \
            processor.iserver.lookup_external_session(header.AuthenticationToken)
        if not isinstance(token, ua.UserNameIdentityToken) or session is None:
            return  # anonymous, or no session: asyncua decides
        mode = processor._connection.security_policy.Mode
        if not token.EncryptionAlgorithm and mode != ua.MessageSecurityMode.SignAndEncrypt:
            # Part 4, 7.41: the token policy names Basic256Sha256, so the password must come
            # encrypted with the server's certificate; sent in clear it is refused, unread.
            await self.recorder.record(
                {"user": str(token.UserName or "")[:32], "via": "failed", "peer": peer},
                "login", "failed", ua.StatusCodes.BadIdentityTokenRejected,
                {"reason": "a password sent unencrypted on an unencrypted channel"})
            raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)
        try:
            name, password = processor.iserver.decrypt_user_token(session, token)
        except Exception:
            return  # asyncua answers BadIdentityTokenInvalid
        name = str(name or "")
        outcome = await self.users.login(name, str(password), peer)
        if outcome is Login.FAILED:
            await self.recorder.record({"user": name[:32], "via": "failed", "peer": peer},
                                       "login", "failed", ua.StatusCodes.BadUserAccessDenied,
                                       {"reason": "a wrong user name or password"})
        if outcome is not Login.OK:
            raise ServiceError(ua.StatusCodes.BadUserAccessDenied)

    def _background(self, work: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


def _check_session_certificate(processor: UaProcessor, body: Buffer) -> None:
    """Part 4 (CreateSession): on a secured channel the ClientCertificate is the channel's
    own, and its SubjectAltName holds the ApplicationUri the client describes itself with."""
    policy = processor._connection.security_policy
    if policy.Mode == ua.MessageSecurityMode.None_:
        return
    params = struct_from_binary(ua.CreateSessionParameters, body.copy())
    sent = first_certificate(params.ClientCertificate or b"")
    if not sent or sent != policy.peer_certificate:
        raise ServiceError(ua.StatusCodes.BadCertificateInvalid)
    try:
        cert = x509.load_der_x509_certificate(sent)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
    except (ValueError, x509.ExtensionNotFound):
        raise ServiceError(ua.StatusCodes.BadCertificateInvalid) from None
    uri = params.ClientDescription.ApplicationUri if params.ClientDescription else None
    if uri not in san.value.get_values_for_type(x509.UniformResourceIdentifier):
        raise ServiceError(ua.StatusCodes.BadCertificateUriInvalid)
