"""TLS for the service's channels: server credentials, client credentials, and
which addresses may be served without them.

    creds = server_credentials(cert, key, client_ca=ca)   # deepcontact serve
    channel_creds = credentials_from_args(args)           # any client command
    is_local_bind("127.0.0.1:50051")                      # True: plaintext is fine

The files are PEM. Each is read and checked here, with Python's `ssl` (a
certificate that is not PEM, a key that does not belong to its certificate),
so that a wrong file is a one-line error naming it at start, not a handshake
that fails later with a message from the TLS library about neither file.
Errors are ValueError with a one-line message.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import ssl
from pathlib import Path

import grpc

PathLike = str | os.PathLike


def add_client_arguments(parser: argparse.ArgumentParser) -> None:
    """--tls-ca, --tls-cert, --tls-key: how a client command dials a TLS server."""
    parser.add_argument("--tls-ca", type=Path, metavar="FILE",
                        help="PEM root certificates to verify the server by (its CA). Giving any of --tls-ca, "
                             "--tls-cert, --tls-key dials with TLS; without --tls-ca the system's roots verify it")
    parser.add_argument("--tls-cert", type=Path, metavar="FILE",
                        help="PEM certificate chain this client presents, for a server that requires client "
                             "certificates (deepcontact serve --tls-client-ca); with --tls-key")
    parser.add_argument("--tls-key", type=Path, metavar="FILE", help="PEM private key of --tls-cert")


def credentials_from_args(args: argparse.Namespace) -> grpc.ChannelCredentials | None:
    """client_credentials from the flags add_client_arguments added (None: plaintext)."""
    return client_credentials(getattr(args, "tls_ca", None), getattr(args, "tls_cert", None),
                              getattr(args, "tls_key", None))


def client_credentials(ca: PathLike | None = None, cert: PathLike | None = None,
                       key: PathLike | None = None) -> grpc.ChannelCredentials | None:
    """Channel credentials: verify the server by `ca` (the system's roots when None) and,
    with `cert` and `key`, present that certificate. None when all three are None
    (a plaintext channel). ValueError for a certificate without its key (or the reverse)
    or a file that cannot be read or is not what it should be."""
    if ca is None and cert is None and key is None:
        return None
    if (cert is None) != (key is None):
        raise ValueError("--tls-cert and --tls-key go together (a client certificate and its key)")
    roots = _read_pem(ca, "--tls-ca") if ca is not None else None
    if roots is not None:
        _check_roots(ca, "--tls-ca")
    chain = private_key = None
    if cert is not None:
        chain, private_key = _read_pem(cert, "--tls-cert"), _read_pem(key, "--tls-key")
        _check_pair(cert, key)
    return grpc.ssl_channel_credentials(root_certificates=roots, private_key=private_key, certificate_chain=chain)


def server_credentials(cert: PathLike, key: PathLike, client_ca: PathLike | None = None) -> grpc.ServerCredentials:
    """Server credentials from a PEM certificate chain and its key; with `client_ca`,
    every client must present a certificate that CA signed (mutual TLS), and a client
    without one is refused in the handshake. ValueError for a file that cannot be read
    or does not fit (a key of another certificate)."""
    chain, private_key = _read_pem(cert, "--tls-cert"), _read_pem(key, "--tls-key")
    _check_pair(cert, key)
    roots = None
    if client_ca is not None:
        roots = _read_pem(client_ca, "--tls-client-ca")
        _check_roots(client_ca, "--tls-client-ca")
    return grpc.ssl_server_credentials([(private_key, chain)], root_certificates=roots,
                                       require_client_auth=roots is not None)


def is_local_bind(bind: str) -> bool:
    """Whether a `deepcontact serve --bind` address is reachable from this machine only:
    a Unix socket (unix:PATH, unix-abstract:NAME), localhost, or a loopback IP
    (127.0.0.0/8, ::1). A host name other than localhost may resolve to anything, and an
    empty host or 0.0.0.0 / [::] listens on every interface: not local."""
    if bind.startswith(("unix:", "unix-abstract:")):
        return True
    host = bind.rsplit(":", 1)[0] if ":" in bind else bind
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if host.lower() == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped  # ::ffff:127.0.0.1
    return address.is_loopback


def _read_pem(path: PathLike, flag: str) -> bytes:
    """The bytes of a PEM file; ValueError naming the file (and its flag) when it cannot
    be read or holds no PEM block."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"{flag} {path}: cannot read it ({exc.strerror or exc})") from None
    if b"-----BEGIN " not in data:
        raise ValueError(f"{flag} {path}: not a PEM file (no -----BEGIN line)")
    return data


def _check_pair(cert: PathLike, key: PathLike) -> None:
    """ValueError unless `key` is an unencrypted PEM key of the certificate in `cert`
    (gRPC takes no passphrase)."""
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(os.fspath(cert), os.fspath(key),
                                                                password=lambda: b"")
    except ssl.SSLError as exc:
        raise ValueError(f"--tls-cert {cert} and --tls-key {key}: not a certificate and its own unencrypted "
                         f"key ({exc.reason or exc})") from None


def _check_roots(path: PathLike, flag: str) -> None:
    """ValueError unless `path` holds PEM certificates that can verify a peer."""
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_verify_locations(cafile=os.fspath(path))
    except ssl.SSLError as exc:
        raise ValueError(f"{flag} {path}: no certificate in it ({exc.reason or exc})") from None
