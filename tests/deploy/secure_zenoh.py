"""Throwaway TLS certificates, credentials and relocated copies of the deploy/zenoh configs, for the deploy tests.

The configs under deploy/zenoh/ point at the paths the compose file mounts (``/etc/swimm/...``).
Tests load them through Zenoh's own parser, change only those paths, the endpoints and the passwords,
and write the result to a temporary folder, so what is tested is the shipped access control itself.
"""

from __future__ import annotations

import json
import secrets
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

REPO = Path(__file__).resolve().parents[2]
ZENOH_DIR = REPO / "deploy" / "zenoh"
ROLES = ("learner", "eval", "sim", "encoder")


def relocate(config: Path, destination: Path, overrides: dict[str, object]) -> Path:
    """Write ``config`` with ``overrides`` (Zenoh config paths -> values) applied, as JSON Zenoh can read back."""
    loaded = zenoh.Config.from_file(str(config))
    for key, value in overrides.items():
        loaded.insert_json5(key, json.dumps(value))
    destination.write_text(str(loaded))
    return destination


@dataclass
class SecureRouterFiles:
    """A certificate authority, one password per role, and configs for a TLS + ACL router and its clients."""

    folder: Path
    endpoint: str  # tls/localhost:<port>
    passwords: dict[str, str]

    @property
    def router_config(self) -> Path:
        return self.folder / "router.json5"

    def client_config(self, role: str, user: str | None = None, password: str | None = None) -> Path:
        """``role``'s client config; ``user``/``password`` override its credentials (for intruders)."""
        user = user or role
        password = password if password is not None else self.passwords[role]
        return relocate(
            ZENOH_DIR / f"client-tls-{role}.json5",
            self.folder / f"client-{role}-as-{user}-{secrets.token_hex(3)}.json5",
            {
                "transport/link/tls/root_ca_certificate": str(self.folder / "ca.pem"),
                "transport/auth/usrpwd/user": user,
                "transport/auth/usrpwd/password": password,
                "connect/endpoints": [self.endpoint],
            },
        )


def make_secure_router_files(folder: Path, port: int) -> SecureRouterFiles:
    """Certificates from deploy/zenoh/make-certs.sh, fresh passwords, and the relocated router config."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make the test's certificates")
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        ["bash", str(ZENOH_DIR / "make-certs.sh"), str(folder), "localhost"], check=True, capture_output=True
    )
    passwords = {role: secrets.token_urlsafe(12) for role in ROLES}
    credentials = folder / "credentials.txt"
    credentials.write_text("".join(f"{role}:{password}\n" for role, password in passwords.items()))
    endpoint = f"tls/localhost:{port}"
    relocate(
        ZENOH_DIR / "router-tls-acl.json5",
        folder / "router.json5",
        {
            "transport/link/tls/root_ca_certificate": str(folder / "ca.pem"),
            "transport/link/tls/listen_certificate": str(folder / "router.pem"),
            "transport/link/tls/listen_private_key": str(folder / "router-key.pem"),
            "transport/auth/usrpwd/dictionary_file": str(credentials),
            "listen/endpoints": [endpoint],
        },
    )
    return SecureRouterFiles(folder, endpoint, passwords)
