"""TLS for the master–robot link: both sides' configuration sections and their contexts.

TLS is optional. It keeps the link private; it does not admit anyone: both sides still prove the
shared secret in the handshake and authenticate every frame (``docs/protocol.md``), with or
without TLS. A certificate or key that cannot be loaded is a
:class:`~minimize_surprise.errors.ConfigError` naming the file and the configuration key.
"""

from __future__ import annotations

import ssl

from minimize_surprise.config import Strict
from minimize_surprise.errors import ConfigError

__all__ = ["ClientTlsConfig", "ServerTlsConfig", "client_context", "server_context"]


class ServerTlsConfig(Strict, frozen=True):
    """The master's side: its certificate chain and private key.

    With ``ca_file`` the robots must present a client certificate signed by that CA (mutual TLS).
    """

    #: the master's certificate (chain), PEM
    cert_file: str
    #: the private key of that certificate, PEM
    key_file: str
    #: CA certificates, PEM; with it every robot must present a client certificate it signed
    #: (mutual TLS)
    ca_file: str | None = None


class ClientTlsConfig(Strict, frozen=True):
    """A robot's side. Without ``ca_file`` the system's trusted CAs verify the master;
    ``cert_file`` (with ``key_file`` if the key is separate) is the robot's client certificate;
    ``server_hostname`` overrides the name checked in the master's certificate (default: host)."""

    #: CA certificates that verify the master's certificate, PEM (``null``: the system's)
    ca_file: str | None = None
    #: the robot's client certificate, PEM (for a master that requires one)
    cert_file: str | None = None
    #: the private key of ``cert_file``, if not in that file
    key_file: str | None = None
    #: the name checked in the master's certificate (``null``: ``master.host``)
    server_hostname: str | None = None

    def __post_init__(self) -> None:
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("`key_file`: a key needs its certificate in cert_file")


def server_context(tls: ServerTlsConfig, *, key: str = "tls") -> ssl.SSLContext:
    """The master's TLS context; errors name the file and ``<key>.cert_file`` or ``.ca_file``."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        context.load_cert_chain(tls.cert_file, tls.key_file)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(
            f"cannot load the certificate and key: {exc}",
            file=tls.cert_file,
            key=f"{key}.cert_file",
        ) from None
    if tls.ca_file is not None:
        try:
            context.load_verify_locations(cafile=tls.ca_file)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(
                f"cannot load the CA certificates: {exc}", file=tls.ca_file, key=f"{key}.ca_file"
            ) from None
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def client_context(
    tls: ClientTlsConfig, *, file: str | None = None, key: str = "master.tls"
) -> ssl.SSLContext:
    """A robot's TLS context; errors name the configuration ``file`` and ``<key>.ca_file`` or
    ``<key>.cert_file``."""
    try:
        context = ssl.create_default_context(cafile=tls.ca_file)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(
            f"cannot load the CA file {tls.ca_file}: {exc}", file=file, key=f"{key}.ca_file"
        ) from None
    if tls.cert_file is not None:
        try:
            context.load_cert_chain(tls.cert_file, tls.key_file)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(
                f"cannot load the certificate {tls.cert_file} (key {tls.key_file}): {exc}",
                file=file,
                key=f"{key}.cert_file",
            ) from None
    return context
