"""The simulated plant's OPC UA certificates, as a plant's administrator exchanges them.

One directory (0700, keys 0600) holds the simulated control's application certificate,
lathed's (the client the control trusts, by file), a user certificate the control accepts
as a login, and the password of its one account: each side trusts the other's certificate
by its file, nothing is trusted on first use. Made once; a directory that holds them all is
reused as it is (a restarted simulator keeps the certificates lathed already trusts).
Tests make theirs with the same function (docs/machines.md: OPC UA).
"""
from __future__ import annotations

import ipaddress
import os
import secrets
import socket
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

SERVER_URI = "urn:lathed:sim:cnc"        # the simulated control's application URI
CLIENT_URI = "urn:lathed:client"         # lathed's, as the control knows it
USERNAME = "lathed"


@dataclass(frozen=True)
class Pki:
    root: Path

    @property
    def server_cert(self) -> Path:
        return self.root / "cnc-cert.der"

    @property
    def server_key(self) -> Path:
        return self.root / "cnc-key.pem"

    @property
    def client_cert(self) -> Path:
        return self.root / "lathed-cert.der"

    @property
    def client_key(self) -> Path:
        return self.root / "lathed-key.pem"

    @property
    def user_cert(self) -> Path:
        return self.root / "user-cert.der"

    @property
    def user_key(self) -> Path:
        return self.root / "user-key.pem"

    @property
    def password_file(self) -> Path:
        return self.root / "lathed.pass"

    @property
    def trusted_clients(self) -> Path:
        """The control's trust list: the client application certificates it accepts."""
        return self.root / "trusted-clients"

    def password(self) -> str:
        return self.password_file.read_text().splitlines()[0]

    def files(self) -> list[Path]:
        return [self.server_cert, self.server_key, self.client_cert, self.client_key, self.user_cert,
                self.user_key, self.password_file, self.trusted_clients / self.client_cert.name]


def make_certificate(cert: Path, key: Path, uri: str, name: str, server: bool, days: int = 365) -> None:
    """A self-signed OPC UA application (or user) certificate, DER, and its key, PEM (0600)."""
    from asyncua.crypto.cert_gen import (dump_private_key_as_pem, generate_private_key,
                                         generate_self_signed_app_certificate)
    pk = generate_private_key()
    host = socket.gethostname()
    names = [x509.UniformResourceIdentifier(uri), x509.DNSName(host), x509.DNSName("localhost"),
             x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    usage = [ExtendedKeyUsageOID.SERVER_AUTH] if server else [ExtendedKeyUsageOID.CLIENT_AUTH]
    c = generate_self_signed_app_certificate(pk, name, {"organizationName": "lathed simulated plant"},
                                             names, usage, days=days)
    _write(key, dump_private_key_as_pem(pk), 0o600)
    _write(cert, c.public_bytes(Encoding.DER), 0o644)


def ensure_pki(root: Path) -> Pki:
    """The simulated plant's certificates in ``root``, made where any is missing."""
    pki = Pki(Path(root))
    if all(p.exists() for p in pki.files()):
        return pki
    pki.root.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.chmod(pki.root, 0o700)
    make_certificate(pki.server_cert, pki.server_key, SERVER_URI, "lathed simulated CNC", server=True)
    make_certificate(pki.client_cert, pki.client_key, CLIENT_URI, "lathed", server=False)
    make_certificate(pki.user_cert, pki.user_key, f"urn:lathed:user:{USERNAME}", USERNAME, server=False)
    _write(pki.password_file, (secrets.token_urlsafe(18) + "\n").encode(), 0o600)
    pki.trusted_clients.mkdir(exist_ok=True, mode=0o700)
    _write(pki.trusted_clients / pki.client_cert.name, pki.client_cert.read_bytes(), 0o644)
    return pki


def _write(path: Path, data: bytes, mode: int) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(tmp, mode)
    os.replace(tmp, path)
