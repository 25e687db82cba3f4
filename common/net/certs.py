"""TLS material for Zenoh ``tls/`` links: a private CA, the router's certificate, one per role.

``srl certs --out DIR`` (and ``srl up --secure``, into its private temporary directory) calls
:func:`write_tls_material`. What it writes, all PEM, the directory 0700 and every file 0600:

* ``ca.pem`` (the CA certificate: give it to every host) and ``ca.key`` (the CA's private key:
  keep it on the machine that makes certificates; nothing at run time reads it);
* ``router.pem`` / ``router.key``: the router's certificate, for ``localhost``, ``127.0.0.1``,
  ``::1`` and every ``--hosts`` name or address (Zenoh's clients check the name they connect
  to against it: ``verify_name_on_connect`` is on by default);
* ``<role>.pem`` / ``<role>.key`` for every role of :data:`common.net.security.ROLES`, common name =
  the role: the client certificates of mutual TLS (the router refuses a client without one
  signed by this CA).

ECDSA P-256 keys, SHA-256 signatures, 10 years for the CA and 2 for the others (a lab
deployment: re-run ``srl certs`` into a fresh directory to rotate). Pure: no zenoh import; the
``cryptography`` package does the X.509 work.
"""

from __future__ import annotations

import datetime
import ipaddress
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from common.system.checkpoint import write_private

log = logging.getLogger(__name__)

DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")
CA_DAYS = 3650
LEAF_DAYS = 730
ROUTER = "router"


@dataclass(frozen=True)
class TlsFiles:
    """Paths of one directory of TLS material (see the module docstring)."""

    directory: Path

    @property
    def ca(self) -> Path:
        return self.directory / "ca.pem"

    def cert(self, name: str) -> Path:
        return self.directory / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.directory / f"{name}.key"

    def environment(self, name: str) -> dict[str, str]:
        """``SRL_TRANSPORT__TLS_*`` of a process using the certificate ``name`` (a role or router)."""
        return {
            "SRL_TRANSPORT__TLS_CA": str(self.ca),
            "SRL_TRANSPORT__TLS_CERT": str(self.cert(name)),
            "SRL_TRANSPORT__TLS_KEY": str(self.key(name)),
        }


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "srl"), x509.NameAttribute(NameOID.COMMON_NAME, common_name)]
    )


def _san(hosts: Iterable[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys(hosts):  # unique, in order
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def make_ca(common_name: str = "srl private CA") -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = _key()
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(_name(common_name))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_leaf(
    ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate, common_name: str, hosts: Iterable[str]
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate signed by the CA, usable by a TLS server and client alike (a router also
    connects to other routers), with ``hosts`` as subject alternative names."""
    key = _key()
    now = datetime.datetime.now(datetime.UTC)
    hosts = list(hosts) or [common_name]  # rustls wants a SAN; a role's name serves as one
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=LEAF_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .add_extension(_san(hosts), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def write_tls_material(directory: Path, roles: Iterable[str], hosts: Iterable[str] = ()) -> TlsFiles:
    """A fresh CA, the router's certificate (SANs: :data:`DEFAULT_HOSTS` + ``hosts``) and one
    client certificate per role into ``directory`` (created 0700; refuses to overwrite a file)."""
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    directory.chmod(0o700)
    files = TlsFiles(directory)
    ca_key, ca_cert = make_ca()
    write_private(directory / "ca.key", _key_pem(ca_key))
    write_private(files.ca, _pem(ca_cert))
    leaves = {ROUTER: [*DEFAULT_HOSTS, *hosts], **{role: [role] for role in roles}}
    for name, sans in leaves.items():
        key, cert = make_leaf(ca_key, ca_cert, name, sans)
        write_private(files.key(name), _key_pem(key))
        write_private(files.cert(name), _pem(cert))
    log.info("TLS material in %s: CA, %s", directory, ", ".join(leaves))
    return files
