"""TLS on the yard network: the certificates a router, a cell or a client is configured with, checked
before Zenoh is asked to use them, and what went wrong when a session over `tls/` does not open.

Zenoh reports every failed connection alike ("Unable to connect to any of ..."). A missing, expired or
untrusted certificate, a router that is down and a wrong password need different fixes, so a failure
is diagnosed here with Python's own TLS handshake against the same CA (deploy/README.md)."""

from __future__ import annotations

import json
import re
import socket
import ssl
import stat
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID

WARN_BEFORE = timedelta(days=30)  # doctor and router warn this long before a certificate expires
ENDPOINT = re.compile(r"^(tcp|tls|udp|quic|ws|unixsock-stream)/(\[[^\]]+\]|[^:/\[]+):(\d+)")


class CertificateError(ValueError):
    """A certificate or key file is missing, unreadable, malformed, expired or not what it must be."""


def split_endpoint(endpoint: str) -> tuple[str, str, int] | None:
    """(protocol, host, port) of a Zenoh endpoint such as tls/router.yard:7447, or None."""
    m = ENDPOINT.match(endpoint)
    return (m.group(1), m.group(2).strip("[]"), int(m.group(3))) if m else None


def is_tls(endpoint: str) -> bool:
    return endpoint.startswith(("tls/", "quic/"))


def _read(path: str | Path, what: str) -> bytes:
    p = Path(path)
    if not p.exists():
        raise CertificateError(f"{what} {p} does not exist (deploy/make-certs.sh makes it)")
    if not p.is_file():
        raise CertificateError(f"{what} {p} is not a file")
    try:
        return p.read_bytes()
    except OSError as e:
        raise CertificateError(f"{what} {p} cannot be read: {e.strerror}") from None


def load_certificates(path: str | Path, what: str = "certificate") -> list[x509.Certificate]:
    """Every certificate in a PEM file (a CA file may hold two while the CA is rotated)."""
    data = _read(path, what)
    try:
        certs = x509.load_pem_x509_certificates(data)
    except ValueError:
        certs = []
    if not certs:
        raise CertificateError(f"{what} {path} holds no PEM certificate (expected '-----BEGIN CERTIFICATE-----')")
    return certs


def describe(cert: x509.Certificate) -> str:
    return f"'{cert.subject.rfc4514_string()}' (valid {cert.not_valid_before_utc:%Y-%m-%d} to " \
           f"{cert.not_valid_after_utc:%Y-%m-%d})"


def _check_dates(cert: x509.Certificate, path: str | Path, what: str, now: datetime) -> list[str]:
    if now > cert.not_valid_after_utc:
        raise CertificateError(f"{what} {path} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC: "
                               f"{describe(cert)}; make a new one (deploy/make-certs.sh, 'Rotation')")
    if now < cert.not_valid_before_utc:
        raise CertificateError(f"{what} {path} is not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC "
                               f"(is this computer's clock right? it says {now:%Y-%m-%d %H:%M} UTC)")
    left = cert.not_valid_after_utc - now
    return [f"{what} {path} expires in {left.days} days ({cert.not_valid_after_utc:%Y-%m-%d}): "
            f"renew it (deploy/make-certs.sh)"] if left < WARN_BEFORE else []


def check_ca(path: str | Path, now: datetime | None = None) -> list[str]:
    """Raises CertificateError unless ``path`` holds CA certificates of which at least one is in date;
    returns warnings (one expiring soon, one already expired beside a valid one)."""
    now = now or datetime.now(timezone.utc)
    certs = load_certificates(path, "CA certificate")
    warnings, valid = [], 0
    for c in certs:
        try:
            bc = c.extensions.get_extension_for_class(x509.BasicConstraints).value
        except x509.ExtensionNotFound:
            bc = None
        if not (bc and bc.ca):
            raise CertificateError(f"CA certificate {path}: {describe(c)} is not a CA certificate (basicConstraints "
                                   f"CA:TRUE); give the yard CA's ca.crt, not the router's certificate")
        try:
            warnings += _check_dates(c, path, "CA certificate", now)
            valid += 1
        except CertificateError as e:
            if len(certs) == 1:
                raise
            warnings.append(str(e))
    if not valid:
        raise CertificateError(f"every CA certificate in {path} is out of date")
    return warnings


def _key_mode(path: Path) -> list[str]:
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o007:
        raise CertificateError(f"private key {path} is readable by every user (mode {mode:o}): chmod 600 {path}")
    return [f"private key {path} is readable by its group (mode {mode:o}); 600 is safer"] if mode & 0o070 else []


def check_server_pair(cert_path: str | Path, key_path: str | Path, now: datetime | None = None,
                      who: str = "router") -> list[str]:
    """A server's own certificate and key (``who``: the router, the tablet app): in date, a server
    certificate, the key its certificate names, and a key no other user can read. Raises
    CertificateError; returns warnings."""
    now = now or datetime.now(timezone.utc)
    cert = load_certificates(cert_path, f"{who} certificate")[0]
    warnings = _check_dates(cert, cert_path, f"{who} certificate", now)
    data = _read(key_path, f"{who} private key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as e:
        raise CertificateError(f"{who} private key {key_path} is not an unencrypted PEM private key ({e})") from None
    pub = serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(serialization.Encoding.DER, pub) != \
            cert.public_key().public_bytes(serialization.Encoding.DER, pub):
        raise CertificateError(f"{who} private key {key_path} does not belong to the certificate {cert_path}")
    try:
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        if ExtendedKeyUsageOID.SERVER_AUTH not in eku:
            raise CertificateError(f"{who} certificate {cert_path} is not a server certificate (extendedKeyUsage "
                                   f"lacks serverAuth)")
    except x509.ExtensionNotFound:
        pass
    if not names(cert):
        raise CertificateError(f"{who} certificate {cert_path} names no host (no subjectAltName): clients "
                               f"verify the {who}'s name against it")
    return warnings + _key_mode(Path(key_path))


def names(cert: x509.Certificate) -> list[str]:
    """The DNS names and IP addresses a server certificate is valid for."""
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    return san.get_values_for_type(x509.DNSName) + [str(a) for a in san.get_values_for_type(x509.IPAddress)]


@dataclass(frozen=True)
class Probe:
    """What a TLS handshake to an endpoint found: ``kind`` is "ok", "down" (nothing accepts a
    connection there), "certificate" (the router's certificate is refused: expired, untrusted, wrong
    name) or "not-tls" (something answers there, but not TLS)."""

    endpoint: str
    kind: str
    message: str = ""
    warning: str = ""  # "ok", but the router's certificate expires within WARN_BEFORE


_VERIFY = {
    10: "the router's certificate has expired",
    9: "the router's certificate is not valid yet (check this computer's clock)",
    62: "the router's certificate is not valid for this name",
    64: "the router's certificate is not valid for this address",
}


def probe(endpoint: str, ca_file: str | Path, timeout_s: float = 3.0) -> Probe:
    """A TLS handshake to ``endpoint`` that verifies the router's certificate against ``ca_file`` and the
    endpoint's host name, the way Zenoh's client does."""
    parsed = split_endpoint(endpoint)
    if not parsed:
        return Probe(endpoint, "down", f"{endpoint} is not a host:port endpoint")
    _, host, port = parsed
    try:
        ctx = ssl.create_default_context(cafile=str(ca_file))
    except (OSError, ssl.SSLError) as e:
        return Probe(endpoint, "certificate", f"the CA file {ca_file} cannot be used: {e}")
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as e:
        return Probe(endpoint, "down", f"nothing accepts a connection at {host}:{port} ({e.strerror or e})")
    try:
        with ctx.wrap_socket(sock, server_hostname=host) as tls:
            cert = tls.getpeercert()
        ends = datetime.fromtimestamp(ssl.cert_time_to_seconds(cert["notAfter"]), timezone.utc)
        left = ends - datetime.now(timezone.utc)
        warning = f"the router's certificate at {endpoint} expires in {left.days} days ({ends:%Y-%m-%d}): renew it " \
                  f"(deploy/README.md, Certificates)" if left < WARN_BEFORE else ""
        return Probe(endpoint, "ok", f"the router's certificate is trusted and valid for {host} (expires "
                                     f"{ends:%Y-%m-%d})", warning)
    except ssl.SSLCertVerificationError as e:
        why = _VERIFY.get(e.verify_code) or (
            f"the router's certificate is not signed by the CA in {ca_file}" if e.verify_code in (2, 18, 19, 20, 21)
            else e.verify_message)
        if e.verify_code in (62, 64):
            why += f" '{host}' (connect with a name or address its certificate lists: deploy/make-certs.sh show)"
        return Probe(endpoint, "certificate", f"{endpoint}: {why}")
    except (ssl.SSLError, OSError) as e:
        return Probe(endpoint, "not-tls", f"{endpoint} accepts connections but the TLS handshake failed ({e}); "
                                          f"is it a plain tcp/ listener?")
    finally:
        sock.close()


def config_value(conf, key: str):
    """A setting of a Zenoh config (``zenoh.Config``), or None where it is not set."""
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - no such setting
        return None


def configured_ca(conf) -> str | None:
    """The CA certificate file a Zenoh config trusts for tls/ links, if any."""
    return config_value(conf, "transport/link/tls/root_ca_certificate") or None


def speaks_tls(endpoint: str, timeout_s: float = 3.0) -> bool:
    """Whether a TLS server answers at ``endpoint`` (certificate not checked): a client that said tcp/ to
    a router that listens on TLS only is told to say tls/."""
    parsed = split_endpoint(endpoint)
    if not parsed:
        return False
    ctx = ssl.create_default_context()
    ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
    try:
        with socket.create_connection(parsed[1:], timeout=timeout_s) as sock, \
                ctx.wrap_socket(sock, server_hostname=parsed[1]):
            return True
    except (OSError, ssl.SSLError):
        return False
