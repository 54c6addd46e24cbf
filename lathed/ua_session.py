"""An OPC UA session to a machine's control, secured as plants require (docs/machines.md).

Security is Sign or SignAndEncrypt with Basic256Sha256 or one of the two newer RSA policies;
lathed's application certificate and key are files, and the control's certificate is trusted
by its file alone: before the channel is opened the certificate the server presents is
compared with it, and a different one (another server at that address, a renewed certificate
nobody has trusted yet) is refused, never learnt. A session logs in with a user name and the
password from a file (0600), or with a user certificate. Every refusal is one line that says
which side refused what. Security "None" is for a server on loopback only.
"""
from __future__ import annotations

import asyncio
import hashlib
import ipaddress
import stat
from pathlib import Path
from urllib.parse import urlparse

from asyncua import Client, ua
from asyncua.crypto import security_policies as sp
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from lathed.config import Section

POLICIES = {"Basic256Sha256": sp.SecurityPolicyBasic256Sha256,
            "Aes128Sha256RsaOaep": sp.SecurityPolicyAes128Sha256RsaOaep,
            "Aes256Sha256RsaPss": sp.SecurityPolicyAes256Sha256RsaPss}
MODES = {"Sign": ua.MessageSecurityMode.Sign, "SignAndEncrypt": ua.MessageSecurityMode.SignAndEncrypt,
         "None": ua.MessageSecurityMode.None_}
LOGIN_REFUSED = ("BadUserAccessDenied", "BadIdentityTokenInvalid", "BadIdentityTokenRejected",
                 "BadUserSignatureInvalid")
CERT_REFUSED = ("BadCertificateUntrusted", "BadCertificateInvalid", "BadCertificateUriInvalid",
                "BadCertificateTimeInvalid", "BadCertificateUseNotAllowed", "BadCertificateRevoked",
                "BadSecurityChecksFailed", "BadCertificateIssuerRevocationUnknown",
                "BadCertificateRevocationUnknown", "BadCertificateChainIncomplete")


class Refused(ConnectionError):
    """The server, or lathed, refused the session: someone must act (a certificate, an account)."""


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def thumbprint(der: bytes) -> str:
    """SHA-1 over the DER, as OPC UA tools show a certificate's thumbprint."""
    return hashlib.sha1(der).hexdigest().upper()


class Security:
    """The session's keys of a machine's table: url, security, policy, the certificate files,
    the login. Paths are relative to the config file; the files are read at each connect (a
    renewed certificate is taken without a restart), so errors about them come then."""

    def __init__(self, section: Section):
        here = Path(section.file).parent
        self.section = section
        self.url = section.getstr("url")
        u = urlparse(self.url)
        if u.scheme != "opc.tcp" or not u.hostname:
            raise section.error("url", f"{self.url!r} is not opc.tcp://HOST:PORT[/PATH]")
        self.where = self.url
        self.mode = section.getstr("security", "SignAndEncrypt", choices=tuple(MODES))
        self.policy = section.getstr("policy", "Basic256Sha256", choices=tuple(POLICIES))
        if self.mode == "None" and not _loopback(u.hostname):
            raise section.error("security", f"None sends every value and the login in clear: only to a server on "
                                            f"this computer (loopback), not {u.hostname}; use Sign or SignAndEncrypt")

        secure = self.mode != "None"
        need = f"security {self.mode}" if secure else None
        self.certificate = _path(section, here, "certificate", need)
        self.private_key = _path(section, here, "private_key", need)
        # the control's own certificate: the only one trusted for this machine
        self.server_certificate = _path(section, here, "server_certificate", need)
        if not secure and (self.certificate or self.private_key or self.server_certificate):
            raise section.error("security", "is None but certificates are given: give Sign or SignAndEncrypt")
        self.username = section.getstr("username", "") or None
        self.password_file = _path(section, here, "password_file", None)
        if bool(self.username) != bool(self.password_file):
            raise section.error("username" if not self.username else "password_file",
                                "missing: a login by name needs username and password_file (its first line)")
        self.user_certificate = _path(section, here, "user_certificate", None)
        self.user_private_key = _path(section, here, "user_private_key", None)
        if bool(self.user_certificate) != bool(self.user_private_key):
            raise section.error("user_certificate" if not self.user_certificate else "user_private_key",
                                "missing: a login by certificate needs user_certificate and user_private_key")
        if self.username and self.user_certificate:
            raise section.error("user_certificate", "and username are both given: log in one way")
        if self.user_certificate and not secure:
            raise section.error("user_certificate", "a login by certificate needs security Sign or SignAndEncrypt")
        self.login = (f"user {self.username!r}" if self.username else
                      "the user certificate" if self.user_certificate else "anonymous")

    def describe(self) -> str:
        return "None" if self.mode == "None" else f"{self.policy} {self.mode}"

    # -- files ---------------------------------------------------------------
    def _read(self, key: str, p: Path, secret: bool = False) -> bytes:
        try:
            if secret and stat.S_IMODE(p.stat().st_mode) & 0o007:
                raise self.section.error(key, f"{p}: readable by every user (mode "
                                              f"{stat.S_IMODE(p.stat().st_mode):04o}): chmod 600 it")
            return p.read_bytes()
        except FileNotFoundError:
            raise self.section.error(key, f"{p}: no such file") from None
        except OSError as e:
            raise self.section.error(key, f"{p}: cannot be read ({e.strerror or e})") from None

    def _cert(self, key: str, p: Path) -> x509.Certificate:
        data = self._read(key, p)
        try:
            return x509.load_der_x509_certificate(data) if not data.lstrip().startswith(b"-----") \
                else x509.load_pem_x509_certificate(data)
        except ValueError as e:
            raise self.section.error(key, f"{p}: not a certificate (DER or PEM): {e}") from None

    def _password(self) -> str:
        lines = self._read("password_file", self.password_file, secret=True).decode(errors="replace").splitlines()
        if not lines or not lines[0]:
            raise self.section.error("password_file", f"{self.password_file}: empty: the first line is the password")
        return lines[0]

    # -- the session ---------------------------------------------------------
    async def open(self, name: str, timeout: float, session_timeout_s: float) -> Client:
        """A connected client, or ConfigError (a file), Refused (someone must act) or
        ConnectionError (the server not there), each one line."""
        # asyncua's own health probe (a read every watchdog_intervall) is left out: the
        # subscription's keep-alives tell a dead link (the driver's stale_after), a closed one
        # is seen as it closes
        client = Client(self.url, timeout=timeout, watchdog_intervall=24 * 3600.0)
        client.name = client.description = f"lathed {name}"
        client.product_uri = "urn:lathed"
        client.session_timeout = int(session_timeout_s * 1000)
        if self.mode != "None":
            await self._secure(client)
        if self.username:
            client.set_user(self.username)
            client.set_password(self._password())
        elif self.user_certificate:
            self._cert("user_certificate", self.user_certificate)
            self._read("user_private_key", self.user_private_key, secret=True)
            await client.load_client_certificate(str(self.user_certificate))
            await client.load_private_key(self.user_private_key)
        try:
            await client.connect()
        except ua.UaStatusCodeError as e:
            await close_quietly(client)
            code = type(e).__name__
            if code in LOGIN_REFUSED:
                raise Refused(f"the OPC UA server at {self.url} refused the login of {self.login} ({code}: "
                              "wrong password, no such account, or not allowed on this endpoint)") from None
            if code in CERT_REFUSED:
                raise Refused(f"the OPC UA server at {self.url} refused lathed's certificate {self.certificate} "
                              f"({code}): put it in the control's trusted certificates") from None
            raise ConnectionError(f"the OPC UA server at {self.url} refused the session: {code}") from None
        except ua.UaError as e:
            await close_quietly(client)
            raise Refused(f"the OPC UA server at {self.url} answered with another certificate than "
                          f"{self.server_certificate} ({e}): not the trusted control") from None
        except (OSError, asyncio.TimeoutError) as e:
            await close_quietly(client)
            raise ConnectionError(f"no OPC UA session with {self.url}: {type(e).__name__} {e} "
                                  "(machine off, network down, or the server does not trust lathed?)") from None
        return client

    async def _secure(self, client: Client) -> None:
        cert = self._cert("certificate", self.certificate)
        self._read("private_key", self.private_key, secret=True)
        trusted = self._cert("server_certificate", self.server_certificate).public_bytes(Encoding.DER)
        try:
            uris = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value \
                .get_values_for_type(x509.UniformResourceIdentifier)
        except x509.ExtensionNotFound:
            uris = []
        if not uris:
            raise self.section.error("certificate", f"{self.certificate}: no application URI (subjectAltName URI): "
                                                    "an OPC UA application certificate names its application")
        client.application_uri = uris[0]     # the server checks the two agree
        # what the server presents, before any key is used: only the trusted one is accepted
        try:
            endpoints = await client.connect_and_get_server_endpoints()
        except (OSError, asyncio.TimeoutError, ua.UaError) as e:
            raise ConnectionError(f"no OPC UA server at {self.url}: {type(e).__name__} {e} "
                                  "(machine off or network down?)") from None
        mode, policy = MODES[self.mode], POLICIES[self.policy]
        offered = [ep for ep in endpoints if ep.SecurityMode == mode and ep.SecurityPolicyUri == policy.URI]
        if not offered:
            have = sorted({f"{ep.SecurityPolicyUri.rsplit('#', 1)[-1]} {ep.SecurityMode.name}" for ep in endpoints})
            raise Refused(f"the OPC UA server at {self.url} offers no {self.describe()} endpoint "
                          f"(it offers: {', '.join(have) or 'none'})")
        presented = _first_cert(offered[0].ServerCertificate or b"")
        if presented != trusted:
            raise Refused(f"the OPC UA server at {self.url} presents certificate {thumbprint(presented)[:16]}..., "
                          f"not the trusted {thumbprint(trusted)[:16]}... in {self.server_certificate}: refused "
                          "(another server at that address, or a new certificate to trust by hand)")
        await client.set_security(policy, str(self.certificate), str(self.private_key),
                                  server_certificate=trusted, mode=mode)


def _path(section: Section, here: Path, key: str, needed_by: str | None) -> Path | None:
    """A file's path from the config, relative to it; ``needed_by``: what makes it required."""
    text = section.getstr(key, "")
    if not text:
        if needed_by:
            raise section.error(key, f"missing: {needed_by} needs it")
        return None
    p = Path(text)
    return p if p.is_absolute() else here / p


def _first_cert(der: bytes) -> bytes:
    """A server may send its certificate chain: the first certificate is its own."""
    if len(der) < 4:
        return der
    return der[:int.from_bytes(der[2:4], "big") + 4]


async def close_quietly(client: Client) -> None:
    try:
        await asyncio.wait_for(client.disconnect(), 2.0)
    except Exception:   # half-open: nothing to close cleanly
        pass
