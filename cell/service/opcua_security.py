"""OPC UA beyond loopback: only the configured security, trusted clients, users with roles,
and limits so that no client can starve the others.

asyncua (2.1) on its own falls back to its default SecurityPolicy None whenever a client
asks for it, even when the server offers only Basic256Sha256 SignAndEncrypt: a None
channel with a plain-text user name token gets a session, and Halt returns Good. It also
keeps a session whose connection dropped for up to its timeout (ten minutes by default),
so clients that subscribe and vanish hold every session slot. `GuardedServer` is an
asyncua Server whose every connection goes through `GuardedProcessor`:

- channel: an OpenSecureChannel whose policy URI or mode is not configured is answered with
  an error and the connection closed; a None channel serves discovery only (GetEndpoints,
  FindServers, which every client uses to fetch the server's certificate, as the spec
  requires) and is closed at any other request, CreateSession first; the client's
  certificate must be in `trusted_clients_dir` (an exact copy, .der or .pem), an unknown one
  is saved to `rejected_clients_dir` for an admin to approve (move it over, no restart: the
  folder is read again when it changes);
- session: one per connection; CreateSession's certificate must be the channel's and carry
  the application URI the client claims; a user name token is accepted only encrypted
  (a SignAndEncrypt channel, or the password encrypted with the policy), checked off the
  event loop against the users (cell.access.users) after the login throttle
  (cell.access.throttle: each try counts as it begins, so parallel guesses get no more checks);
  the session's user carries the cell's Role and the fingerprint of their entry in the users
  file (cell.access.users.Authenticator.credential): a user removed or given another role or
  password has every request refused (BadUserAccessDenied) and their session and connection
  closed, at their next request or within USERS_CHECK_S, whichever comes first;
- limits: connections per client address and in total, a deadline to activate a session,
  a cap on the session timeout a client may ask for, subscriptions per session, and a
  session closed as soon as its connection drops (a client reconnecting makes a new one).

The method handlers of cell.service.opcua and cell.service.machinevision build the caller's
Origin with `caller_origin()`: the session's user and role, capped at
`service.machine_vision.client_role` (without users, loopback only: that role); a caller
without a role, or a call that is no client's request, gets None and is refused everything.
"""

from __future__ import annotations

import asyncio
import contextvars
import datetime as dt
import hashlib
import hmac
import logging
import re
import socket
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from asyncua import Server, ua
from asyncua.common.utils import Buffer
from asyncua.crypto import uacrypto
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_session import InternalSession, SessionState
from asyncua.server.uaprocessor import UaProcessor
from asyncua.server.user_managers import UserManager
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary, uatcp_to_binary
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from cell.access.throttle import LoginThrottle
from cell.atomicfile import write_bytes_atomic
from cell.core.events import Interface, Origin, Role
from cell.logratelimit import Tally
from cell.service.ua_values import node_id, status

log = logging.getLogger(__name__)

_OPEN = ua.MessageType.SecureOpen
_NONE_URI = "http://opcfoundation.org/UA/SecurityPolicy#None"
_ENCRYPTED = ua.MessageSecurityMode.SignAndEncrypt
MAX_REJECTED_SAVED = 200  # certificates kept in rejected/ (an attacker may send many)
HASH_CHECKS_AT_ONCE = 2  # password hashes computed at once (2 cores: the cell keeps one)


def _request(name: str) -> ua.NodeId:
    return node_id(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))


_CREATE_SESSION, _ACTIVATE_SESSION, _CREATE_SUBSCRIPTION = (
    _request("CreateSession"),
    _request("ActivateSession"),
    _request("CreateSubscription"),
)
_DISCOVERY = frozenset({_request("GetEndpoints"), _request("FindServers")})
_SESSION_SERVICES = _DISCOVERY | {_CREATE_SESSION, _ACTIVATE_SESSION, _request("CloseSession")}
USERS_CHECK_S = 1.0  # how often open sessions are compared with the users file (a removed user's end)


# ---- who is calling ----------------------------------------------------------------------
@dataclass
class CellUser(User):
    """asyncua's user, with the cell's role (what the command table checks)."""

    cell_role: Role = Role.VIEWER
    # the user's fingerprint at login (Authenticator.credential): when it changes, the session ends
    credential: str | None = None


@dataclass(frozen=True)
class _Caller:
    user: User | None
    address: str
    role: Role | None  # what the caller may do: None, nothing at all


_CALLER: contextvars.ContextVar[_Caller | None] = contextvars.ContextVar("opcua_caller", default=None)
_VERIFIED: contextvars.ContextVar[tuple[str, str, Role | None, str | None] | None] = contextvars.ContextVar(
    "opcua_verified_login", default=None
)


def caller_role(user: User | None, secure: bool, client_role: Role) -> Role | None:
    """The role an OPC UA session acts with. `client_role` (service.machine_vision.client_role)
    is the most any OPC UA client may do: a logged-in user acts with their own role, capped at
    it; without users (loopback only) the anonymous local client acts with it. A session on a
    secure server without a user of the cell has no role (None): it may do nothing."""
    if isinstance(user, CellUser):
        return user.cell_role if user.cell_role.rank <= client_role.rank else client_role
    if secure:
        return None
    return client_role


def caller_origin() -> Origin | None:
    """The Origin of the OPC UA request being handled (call it from an async method handler), or
    None when it may do nothing: a caller without a role, or a call that is not a client's request
    on a GuardedServer at all (deny by default: every handler refuses it, BadUserAccessDenied)."""
    caller = _CALLER.get()
    if caller is None or caller.role is None:
        return None
    name = (caller.user.name or "") if isinstance(caller.user, CellUser) else ""
    return Origin(Interface.OPCUA, name, caller.role, caller.address)


class CellUserManager(UserManager):
    """asyncua user manager: answers from the login GuardedProcessor verified off the event loop."""

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> CellUser | None:
        verified = _VERIFIED.get()
        if verified is None or username is None or password is None:
            log.error("OPC UA: a login reached the user manager without being checked first: refused")
            return None
        name, secret, role, credential = verified
        if name != username or not hmac.compare_digest(secret.encode(), password.encode()) or role is None:
            return None
        return CellUser(role=UserRole.User, name=username, cell_role=role, credential=credential)


# ---- the trust list ------------------------------------------------------------------------
def first_der(blob: bytes) -> bytes:
    """The first DER element of a certificate chain (a client may send its chain after its own)."""
    if len(blob) < 2 or blob[0] != 0x30:
        raise ValueError("not a DER certificate")
    length, start = blob[1], 2
    if length & 0x80:
        count = length & 0x7F
        if count == 0 or count > 4 or len(blob) < 2 + count:
            raise ValueError("bad DER length")
        length, start = int.from_bytes(blob[2 : 2 + count], "big"), 2 + count
    if start + length > len(blob):
        raise ValueError("DER certificate cut short")
    return blob[: start + length]


def _load_certificate(path: Path) -> bytes:
    data = path.read_bytes()
    if path.suffix.lower() == ".pem" or data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data).public_bytes(uacrypto.serialization.Encoding.DER)
    return first_der(data)


class TrustList:
    """Client certificates allowed to connect: exact copies in `trusted_dir`, read again when it changes.
    An unknown certificate is saved to `rejected_dir` (once, at most MAX_REJECTED_SAVED) for an admin to approve."""

    def __init__(self, trusted_dir: Path, rejected_dir: Path) -> None:
        self.trusted_dir, self.rejected_dir = trusted_dir, rejected_dir
        self.trusted_dir.mkdir(parents=True, exist_ok=True)
        self._stamp: tuple[int, int] | None = None
        self._digests: set[bytes] = set()

    def _reload(self) -> None:
        st = self.trusted_dir.stat()
        stamp = (st.st_mtime_ns, st.st_ino)
        if stamp == self._stamp:
            return
        digests = set()
        for path in sorted(self.trusted_dir.iterdir()):
            if path.suffix.lower() not in (".der", ".pem", ".crt", ".cer") or not path.is_file():
                continue
            try:
                digests.add(hashlib.sha256(_load_certificate(path)).digest())
            except (ValueError, OSError) as e:
                log.warning("OPC UA trust list: %s is not a certificate, ignored: %s", path, e)
        self._digests, self._stamp = digests, stamp
        log.info("OPC UA trust list: %d client certificate(s) in %s", len(digests), self.trusted_dir)

    def trusted(self, der: bytes) -> bool:
        self._reload()
        return hashlib.sha256(der).digest() in self._digests

    def reject(self, der: bytes) -> Path | None:
        """Save an unknown certificate for an admin to look at; None when not saved (known, or too many)."""
        digest = hashlib.sha256(der).hexdigest()
        try:
            self.rejected_dir.mkdir(parents=True, exist_ok=True)
            if any(p.name.startswith(digest[:16]) for p in self.rejected_dir.iterdir()):
                return None
            if sum(1 for _ in self.rejected_dir.iterdir()) >= MAX_REJECTED_SAVED:
                return None
            path = self.rejected_dir / f"{digest[:16]}-{_safe_name(der)}.der"
            write_bytes_atomic(path, der)
            return path
        except OSError as e:
            log.warning("OPC UA: cannot save a rejected client certificate in %s: %s", self.rejected_dir, e)
            return None


def _safe_name(der: bytes) -> str:
    try:
        cert = x509.load_der_x509_certificate(der)
        names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
        name = str(names[0].value) if names else "no-cn"
    except ValueError:
        name = "unreadable"
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")[:40] or "no-cn"


def check_client_certificate(der: bytes, claimed_uri: str | None) -> str | None:
    """Why a (trusted) client certificate is not acceptable now, or None: in its validity period,
    and naming the application URI the client claims (when it claims one)."""
    try:
        cert = x509.load_der_x509_certificate(der)
    except ValueError:
        return "the client certificate cannot be read"
    now = dt.datetime.now(dt.UTC)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        return f"the client certificate is valid only {cert.not_valid_before_utc:%Y-%m-%d} to {cert.not_valid_after_utc:%Y-%m-%d}"
    if claimed_uri:
        try:
            san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            uris = san.get_values_for_type(x509.UniformResourceIdentifier)
        except x509.ExtensionNotFound:
            uris = []
        if claimed_uri not in uris:
            return f"the client claims application URI {claimed_uri!r} but its certificate names {uris or 'none'}"
    return None


# ---- settings --------------------------------------------------------------------------------
@dataclass
class GuardSettings:
    """What GuardedServer enforces; `from_config` reads it from the cell's config."""

    secure: bool
    policies: tuple[str, ...] = ("Basic256Sha256_SignAndEncrypt",)
    cert_dir: Path = Path("opcua")
    trusted_dir: Path = Path("opcua/trusted")
    rejected_dir: Path = Path("opcua/rejected")
    app_uri: str = "urn:pick-cell:server"
    max_connections: int = 64
    max_connections_per_address: int = 8
    activation_timeout_s: float = 10.0
    session_timeout_max_s: float = 60.0
    max_subscriptions_per_session: int = 10
    allowed: frozenset[tuple[str, ua.MessageSecurityMode]] = field(default_factory=frozenset)
    client_role: Role = Role.ENGINEER  # the most an OPC UA client may do (service.machine_vision.client_role)

    @classmethod
    def from_config(cls, config: Any, app_uri: str, secure: bool) -> GuardSettings:
        from cell.access.security import certificate_dir

        svc, limits = config.service, config.service.opcua_limits
        cert_dir = certificate_dir(config)
        return cls(
            secure=secure,
            policies=tuple(svc.opcua_security_policies),
            cert_dir=cert_dir,
            trusted_dir=svc.trusted_clients_dir or cert_dir / "trusted",
            rejected_dir=svc.rejected_clients_dir or cert_dir / "rejected",
            app_uri=app_uri,
            max_connections=limits.max_connections,
            max_connections_per_address=limits.max_connections_per_address,
            activation_timeout_s=limits.activation_timeout_s,
            session_timeout_max_s=limits.session_timeout_max_s,
            max_subscriptions_per_session=limits.max_subscriptions_per_session,
            client_role=svc.machine_vision.client_role,
        )

    def policy_types(self) -> list[ua.SecurityPolicyType]:
        return [getattr(ua.SecurityPolicyType, name) for name in self.policies]


def _allowed(types: list[ua.SecurityPolicyType]) -> frozenset[tuple[str, ua.MessageSecurityMode]]:
    from asyncua.crypto.security_policies import SECURITY_POLICY_TYPE_MAP, SecurityPolicy

    allowed = set()
    for t in types:
        # asyncua's map holds [policy class, mode, number] lists, which type-check as list[object]
        policy, mode = cast(type[SecurityPolicy], SECURITY_POLICY_TYPE_MAP[t][0]), SECURITY_POLICY_TYPE_MAP[t][1]
        allowed.add((policy.URI, cast(ua.MessageSecurityMode, mode)))
    return frozenset(allowed)


# ---- the guard ------------------------------------------------------------------------------
class Guard:
    """Shared by every connection of one server: settings, users, throttle, trust list, counts."""

    def __init__(
        self,
        settings: GuardSettings,
        authenticate: Callable[[str, str], Role | None] | None,
        throttle: LoginThrottle | None,
        credential: Callable[[str], str | None] | None = None,
    ) -> None:
        """`credential(user)`: the user's fingerprint now (Authenticator.credential), None once removed."""
        self.settings, self.authenticate, self.throttle = settings, authenticate, throttle
        self.credential = credential
        self.processors: set[GuardedProcessor] = set()  # one per open connection (the sweep of ended users)
        self.allowed = _allowed(settings.policy_types()) if settings.secure else frozenset()
        self.allowed_uris = frozenset(uri for uri, _ in self.allowed)
        self.trust = TrustList(settings.trusted_dir, settings.rejected_dir) if settings.secure else None
        self.per_address: Counter[str] = Counter()
        self.tally = Tally("OPC UA")
        self.hashing = asyncio.Semaphore(HASH_CHECKS_AT_ONCE)

    def user_ended(self, user: User | None) -> bool:
        """True when the session's user was removed or given another role or password since they logged in
        (issue 28: their sessions end at once). Costs a stat of the users file (read again when it changed)."""
        if not isinstance(user, CellUser) or self.credential is None:
            return False
        try:
            now = self.credential(user.name or "")
        except Exception as e:  # an unreadable users file: deny rather than keep a login it cannot check
            log.error("OPC UA: cannot check user %r against the users file, their session ends: %s", user.name, e)
            return True
        return now is None or now != user.credential

    async def end_changed_users(self) -> None:
        """Close every session whose user was removed or changed, with its connection."""
        for processor in list(self.processors):
            session = processor.session
            if session is not None and session.state is SessionState.Activated and self.user_ended(session.user):
                await processor.end_session("ended: its user was removed or changed")

    def check_channel(self, uri: str | None, sender_certificate: bytes | None, address: str) -> int | None:
        """The status code refusing an OpenSecureChannel with this policy and certificate, or None."""
        if not self.settings.secure or uri == _NONE_URI:
            return None  # a None channel: discovery only (GuardedProcessor.process_message)
        if uri not in self.allowed_uris:
            self.tally.note(f"refused: security policy {uri!r} not offered", address)
            return ua.StatusCodes.BadSecurityPolicyRejected
        try:
            der = first_der(sender_certificate or b"")
        except ValueError:
            self.tally.note("refused: no readable client certificate", address)
            return ua.StatusCodes.BadCertificateInvalid
        assert self.trust is not None
        if not self.trust.trusted(der):
            saved = self.trust.reject(der)
            if saved is not None:
                log.warning(
                    "OPC UA: refused an untrusted client certificate from %s, saved as %s: to trust it, "
                    "move it to %s (docs/security.md)",
                    address,
                    saved,
                    self.trust.trusted_dir,
                )
            self.tally.note("refused: untrusted client certificate", address)
            return ua.StatusCodes.BadCertificateUntrusted
        problem = check_client_certificate(der, None)
        if problem:
            self.tally.note(f"refused: {problem}", address)
            return ua.StatusCodes.BadCertificateTimeInvalid
        return None


def _fault(processor: UaProcessor, requesthdr: Any, seqhdr: Any, code: int) -> bool:
    response = ua.ServiceFault()
    response.ResponseHeader.ServiceResult = status(code)
    processor.send_response(requesthdr.RequestHandle, seqhdr, response)  # type: ignore[no-untyped-call]  # untyped in asyncua
    return True


class GuardedProcessor(UaProcessor):
    """asyncua's per-connection processor with the channel, session and login rules of the Guard."""

    def __init__(self, guard: Guard, address: str, *args: Any) -> None:
        super().__init__(*args)
        self.guard, self.address = guard, address

    async def end_session(self, why: str) -> None:
        """Close this connection's session (its subscriptions go) and the connection itself."""
        session = self.session
        if session is None or session.state is SessionState.Closed:
            self._transport.close()
            return
        self.guard.tally.note(why, self.address)
        user = session.user.name if isinstance(session.user, CellUser) else "?"
        log.warning(
            "OPC UA: the session of user %r from %s ended: the user was removed or given another role or password",
            user,
            self.address,
        )
        await session.close_session(True)
        self._transport.close()

    async def process(self, header: Any, body: Buffer) -> bool:
        if header.MessageType == _OPEN and not self._connection.is_open():
            refused = self._refuse_channel(body.copy(header.body_size))
            if refused is not None:
                return self._error(refused)
        try:
            kept = bool(await super().process(header, body))  # type: ignore[no-untyped-call]  # asyncua's UaProcessor is untyped
        except Exception as e:  # asyncua would log it and keep a channel in an unknown state: close it
            if isinstance(e, ua.UaError) and "No matching policy" in str(e):  # asyncua's words for a mode not offered
                self.guard.tally.note("refused: a security mode not offered", self.address)
                return self._error(ua.StatusCodes.BadSecurityModeRejected)
            self.guard.tally.note(f"closed: {type(e).__name__} in the secure channel", self.address)
            return self._error(ua.StatusCodes.BadSecurityChecksFailed)
        if kept and header.MessageType == _OPEN and self.guard.settings.secure:
            policy = self._connection.security_policy
            if (policy.URI, policy.Mode) not in self.guard.allowed and policy.URI != _NONE_URI:
                self.guard.tally.note(f"refused: security mode {policy.Mode.name} not offered", self.address)
                return False
        return kept

    def _refuse_channel(self, data: Buffer) -> int | None:
        try:
            security = struct_from_binary(ua.AsymmetricAlgorithmHeader, data)
        except Exception:
            return ua.StatusCodes.BadDecodingError
        return self.guard.check_channel(security.SecurityPolicyURI, security.SenderCertificate, self.address)

    def _error(self, code: int) -> bool:
        """Tell the client why (an ERR message, as the spec asks) and have the connection closed."""
        err = ua.ErrorMessage(status(code), ua.String(status(code).name))
        # asyncua annotates the message type as the MessageType class; its values are that class's bytes
        self._transport.write(uatcp_to_binary(ua.MessageType.Error, err))  # type: ignore[arg-type]
        return False

    async def process_message(self, seqhdr: Any, body: Buffer) -> bool:
        peek = body.copy()
        typeid = nodeid_from_binary(peek)
        requesthdr = struct_from_binary(ua.RequestHeader, peek)
        if self._discovery_only() and typeid not in _DISCOVERY:
            self.guard.tally.note("closed: a None channel used for more than discovery", self.address)
            _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadSecurityModeInsufficient)
            return False
        user = self.session.user if self.session else None
        if typeid not in _SESSION_SERVICES and self.guard.user_ended(user):
            _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadUserAccessDenied)
            await self.end_session("refused and ended: its user was removed or changed")
            return False
        settings = self.guard.settings
        caller = _CALLER.set(_Caller(user, self.address, caller_role(user, settings.secure, settings.client_role)))
        try:
            if typeid == _CREATE_SESSION:
                refused = self._session_refusal(peek)
                if refused is not None:
                    return _fault(self, requesthdr, seqhdr, refused)
            elif typeid == _ACTIVATE_SESSION and self.guard.settings.secure:
                return await self._activate(seqhdr, body, peek, requesthdr)
            elif (
                typeid == _CREATE_SUBSCRIPTION
                and self._subscriptions() >= self.guard.settings.max_subscriptions_per_session
            ):
                self.guard.tally.note("refused: too many subscriptions in one session", self.address)
                return _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadTooManySubscriptions)
            return bool(await super().process_message(seqhdr, body))  # type: ignore[no-untyped-call]  # untyped in asyncua
        finally:
            _CALLER.reset(caller)

    def _discovery_only(self) -> bool:
        return self.guard.settings.secure and self._connection.security_policy.URI == _NONE_URI

    def _session_refusal(self, peek: Buffer) -> int | None:
        if self.session is not None and self.session.state is not SessionState.Closed:
            self.guard.tally.note("refused: a second session on one connection", self.address)
            return ua.StatusCodes.BadTooManySessions
        if not self.guard.settings.secure:
            return None
        params = struct_from_binary(ua.CreateSessionParameters, peek)
        channel = self._connection.security_policy.peer_certificate
        try:
            same = first_der(params.ClientCertificate or b"") == first_der(channel or b"")
        except ValueError:
            same = False
        if not same:
            self.guard.tally.note("refused: the session's certificate is not the channel's", self.address)
            return ua.StatusCodes.BadCertificateInvalid
        problem = check_client_certificate(first_der(channel or b""), params.ClientDescription.ApplicationUri)
        if problem:
            self.guard.tally.note(f"refused: {problem}", self.address)
            return ua.StatusCodes.BadCertificateUriInvalid
        return None

    async def _activate(self, seqhdr: Any, body: Buffer, peek: Buffer, requesthdr: Any) -> bool:
        """Check the user name token here, off the loop and throttled, then let asyncua activate the session."""
        params = struct_from_binary(ua.ActivateSessionParameters, peek)
        token = params.UserIdentityToken
        session = self.session or self.iserver.lookup_external_session(requesthdr.AuthenticationToken)
        if session is None or not isinstance(token, ua.UserNameIdentityToken):
            return bool(await super().process_message(seqhdr, body))  # type: ignore[no-untyped-call]  # untyped in asyncua, which refuses these itself
        if not token.EncryptionAlgorithm and self._connection.security_policy.Mode != _ENCRYPTED:
            self.guard.tally.note("refused: a password sent unencrypted", self.address)
            return _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadIdentityTokenRejected)
        user = token.UserName or ""
        throttle = self.guard.throttle
        # begin() counts the try at once (issue 28): tries sent in parallel get no further than one after another
        if throttle is not None and throttle.begin(user, self.address) > 0:
            self.guard.tally.note("refused: login throttled", self.address)
            return _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadUserAccessDenied)
        settled = False
        try:
            try:
                name, password = self.iserver.decrypt_user_token(session, token)
            except Exception:
                return _fault(self, requesthdr, seqhdr, ua.StatusCodes.BadIdentityTokenInvalid)
            credential, role = await self._check_password(name or "", password or "")
            if throttle is not None:
                if role is None:
                    throttle.failed(user, self.address, "opcua")
                else:
                    throttle.succeeded(user, self.address)
            settled = True
        finally:
            if throttle is not None and not settled:  # no password checked (a bad token, or the task ended)
                throttle.abandon(user, self.address)
        verified = _VERIFIED.set((name or "", password or "", role, credential))
        try:
            return bool(await super().process_message(seqhdr, body))  # type: ignore[no-untyped-call]  # untyped in asyncua
        finally:
            _VERIFIED.reset(verified)

    async def _check_password(self, name: str, password: str) -> tuple[str | None, Role | None]:
        """(the user's credential fingerprint, read before the check; their role, None if refused)."""
        if self.guard.authenticate is None:
            return None, None
        async with self.guard.hashing:
            return await asyncio.to_thread(self._verify, name, password)

    def _verify(self, name: str, password: str) -> tuple[str | None, Role | None]:
        assert self.guard.authenticate is not None
        # the fingerprint first: a change made during the check then ends the session at its first request
        credential = self.guard.credential(name) if self.guard.credential is not None else None
        return credential, self.guard.authenticate(name, password)

    def _subscriptions(self) -> int:
        if self.session is None:
            return 0
        sid = self.session.session_id
        return sum(1 for s in self.iserver.subscription_service.subscriptions.values() if s.session_id == sid)

    def _should_close_session_on_transport_loss(self) -> bool:
        return True  # reclaimed now, not after its timeout: vanished clients hold nothing


class GuardedProtocol(OPCUAProtocol):
    """asyncua's connection protocol with a cap per client address and a GuardedProcessor."""

    guard: Guard

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if not isinstance(transport, asyncio.Transport):  # what asyncio's TCP server hands a protocol
            raise TypeError(f"OPC UA: a {type(transport).__name__} is not a stream transport")
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if peer else "?"
        self.address: str | None = None
        self.peer_name = peer
        limits = self.guard.settings
        refused = None
        if len(self.clients) >= self.iserver.max_connections:
            refused = f"refused: {self.iserver.max_connections} open connections (max_connections)"
        elif self.guard.per_address[address] >= limits.max_connections_per_address:
            refused = (
                f"refused: {limits.max_connections_per_address} open from one address (max_connections_per_address)"
            )
        if refused is not None:
            self.guard.tally.note(refused, address)
            transport.abort()
            return
        self.address = address
        self.guard.per_address[address] += 1
        self.transport = transport
        self.processor = GuardedProcessor(self.guard, address, self.iserver, self.transport, self.limits)
        self.processor.set_policies(self.policies)  # type: ignore[no-untyped-call]  # untyped in asyncua
        self.guard.processors.add(self.processor)
        self.iserver.asyncio_transports.append(transport)
        self.clients.append(self)
        self._task = asyncio.create_task(self._process_received_message_loop())
        if self.iserver.max_pending_activation_seconds > 0:
            self._activation_watchdog_task = asyncio.create_task(self._activation_watchdog())

    def data_received(self, data: bytes) -> None:
        if len(self._buffer) + len(data) > 2 * self.limits.max_recv_buffer + 64 and self.transport is not None:
            self.guard.tally.note("closed: a message larger than the receive buffer", self.address or "?")
            self.transport.abort()
            return
        super().data_received(data)

    def connection_lost(self, ex: BaseException | None) -> None:
        if isinstance(self.processor, GuardedProcessor):
            self.guard.processors.discard(self.processor)
        if self.address is not None:
            self.guard.per_address[self.address] -= 1
            if self.guard.per_address[self.address] <= 0:
                del self.guard.per_address[self.address]
            self.address = None
        super().connection_lost(ex)


class GuardedBinaryServer(BinaryServer):
    def __init__(self, guard: Guard, *args: Any) -> None:
        super().__init__(*args)
        self.guard = guard

    def _make_protocol(self) -> OPCUAProtocol:
        protocol = GuardedProtocol(
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
        )
        protocol.guard = self.guard
        return protocol


class GuardedServer(Server):
    """An asyncua Server with the Guard's rules. Off loopback (`settings.secure`), call `await secure()`
    before `start()`: certificate (made on first start), the configured policies only, user name
    tokens only, the trust list. Either way `start()` applies the limits and guards every connection."""

    def __init__(
        self,
        settings: GuardSettings,
        authenticate: Callable[[str, str], Role | None] | None = None,
        throttle: LoginThrottle | None = None,
        credential: Callable[[str], str | None] | None = None,
    ) -> None:
        """`credential`: Authenticator.credential; with it a session ends when its user is removed or given another
        role or password (checked at each request and every USERS_CHECK_S)."""
        super().__init__(user_manager=CellUserManager() if settings.secure else None)
        self.guard = Guard(settings, authenticate, throttle, credential)
        self._users_watch: asyncio.Task[None] | None = None

    async def secure(self) -> None:
        s = self.guard.settings
        s.cert_dir.mkdir(parents=True, exist_ok=True)
        key, cert = s.cert_dir / "server-key.pem", s.cert_dir / "server-cert.der"
        await setup_self_signed_certificate(
            key,
            cert,
            s.app_uri,
            socket.gethostname(),
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "pick-cell", "organizationName": "pick-cell"},
        )
        key.chmod(0o600)
        await self.load_certificate(str(cert))
        await self.load_private_key(str(key))
        self.set_security_policy(s.policy_types())
        self.set_identity_tokens([ua.UserNameIdentityToken])

    async def start(self) -> None:
        """asyncua's Server.start with the limits applied and a GuardedBinaryServer listening."""
        s, iserver = self.guard.settings, self.iserver
        if s.secure and iserver.certificate is None:
            raise RuntimeError("GuardedServer: call secure() before start() when settings.secure")
        iserver.allow_remote_admin = False  # no client may change the address space, whatever its name
        iserver.max_connections = s.max_connections
        iserver.max_pending_activation_seconds = s.activation_timeout_s
        iserver.max_session_timeout_ms = s.session_timeout_max_s * 1000
        iserver.min_session_timeout_ms = min(iserver.min_session_timeout_ms, iserver.max_session_timeout_ms)
        iserver.max_subscriptions = min(iserver.max_subscriptions, s.max_connections * s.max_subscriptions_per_session)
        InternalSession.max_connections = s.max_connections  # asyncua counts activated sessions class-wide
        if iserver.certificate is not None:
            uacrypto.check_certificate(iserver.certificate, self._application_uri, socket.gethostname())
        await self._setup_server_nodes()
        await iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = GuardedBinaryServer(self.guard, iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await iserver.stop()
            raise
        if self.guard.credential is not None:
            self._users_watch = asyncio.create_task(self._watch_users(), name="opcua-users-watch")

    async def stop(self) -> None:
        if self._users_watch is not None:
            self._users_watch.cancel()
            await asyncio.gather(self._users_watch, return_exceptions=True)
            self._users_watch = None
        await super().stop()

    async def _watch_users(self) -> None:
        """Sessions of a removed or changed user end even while they send nothing (issue 28)."""
        while True:
            await asyncio.sleep(USERS_CHECK_S)
            try:
                await self.guard.end_changed_users()
            except Exception:  # the watch must go on: the next request's check still holds
                log.exception("OPC UA: checking open sessions against the users file failed")
