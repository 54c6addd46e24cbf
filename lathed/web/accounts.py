"""Accounts of the operator view: users, roles, scrypt password hashes.

A hash is ``scrypt$N$r$p$SALT_HEX$KEY_HEX`` (``lathed-web hash-password``
makes one); only hashes are ever stored in the config.
"""
from __future__ import annotations

import argparse
import getpass
import hashlib
import hmac
import os
import sys

from lathed.config import ConfigError, Section

ROLES = ("viewer", "operator")
N, R, P = 1 << 14, 8, 1     # ~16 MiB and ~50 ms per check: cheap for a login, dear for a guesser


def hash_password(password: str, salt: bytes | None = None) -> str:
    salt = os.urandom(16) if salt is None else salt
    key = hashlib.scrypt(password.encode(), salt=salt, n=N, r=R, p=P, dklen=32)
    return f"scrypt${N}${R}${P}${salt.hex()}${key.hex()}"


def check_hash_format(text: str, tool: str = "lathed-web") -> str | None:
    """Why ``text`` is not a hash this module makes, or None."""
    parts = text.split("$")
    if len(parts) != 6 or parts[0] != "scrypt":
        return f"not an scrypt hash (scrypt$N$r$p$salt$key); make one with `{tool} hash-password`"
    try:
        n, r, p = (int(x) for x in parts[1:4])
        bytes.fromhex(parts[4]), bytes.fromhex(parts[5])
    except ValueError:
        return "a malformed scrypt hash (N, r, p must be integers, salt and key hex)"
    if n < 2 or n & (n - 1) or n > 1 << 20 or not 1 <= r <= 64 or not 1 <= p <= 16:
        return f"scrypt parameters out of range (N={n} must be a power of 2 up to 2**20, r 1..64, p 1..16)"
    return None


def users_from(file: str, tables: object, tool: str = "lathed-web") -> dict[str, tuple[str, str]]:
    """The [users.NAME] tables of a config: name -> (role, password hash); ConfigError names a bad one."""
    users: dict[str, tuple[str, str]] = {}
    for name, table in (tables or {}).items():
        u = Section(file, f"users.{name}", table if isinstance(table, dict) else {})
        role = u.getstr("role", choices=ROLES)
        pw = u.getstr("password")
        u.check_unused()
        if (why := check_hash_format(pw, tool)) is not None:
            raise ConfigError(f"{file}: [users.{name}] password: {why}")
        users[name] = (role, pw)
    return users


def verify(password: str, stored: str) -> bool:
    _, n, r, p, salt, key = stored.split("$")
    want = bytes.fromhex(key)
    got = hashlib.scrypt(password.encode(), salt=bytes.fromhex(salt), n=int(n), r=int(r), p=int(p),
                         dklen=len(want), maxmem=256 << 20)
    return hmac.compare_digest(got, want)


def side_process_args(prog: str, description: str, config_env: str, config_help: str, port: int,
                      argv: list[str] | None, version: str) -> argparse.Namespace | int:
    """The command line shared by the processes beside the daemon (lathed-web, lathed-opcua):
    the namespace to serve with, or, for ``hash-password``, its exit code once the hash is printed."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--config", "-c", default=os.environ.get(config_env),
                   help=f"TOML with [{prog.split('-')[-1]}] and [users.NAME] (default: ${config_env}; {config_help})")
    p.add_argument("--listen", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, help=f"port (default {port})")
    p.add_argument("--socket", help="the daemon's control socket (default: as lathectl finds it)")
    p.add_argument("--version", action="version", version=f"{prog} {version}")
    p.add_argument("command", nargs="?", choices=["serve", "hash-password"], default="serve",
                   help="hash-password: read a password, print its hash for [users.NAME] password")
    args = p.parse_args(argv)
    if args.command != "hash-password":
        return args
    pw = getpass.getpass("password: ") if sys.stdin.isatty() else sys.stdin.readline().rstrip("\n")
    if not pw:
        print(f"{prog}: empty password", file=sys.stderr)
        return 1
    print(hash_password(pw))
    return 0
