"""Who an agent is: a team authority signs one X.509 certificate per agent; revocation by a CRL.

- The **authority** is an Ed25519 key with a self-signed CA certificate: the team's trust
  anchor. It stays with whoever provisions the robots (`erni keys init DIR`).
- An **identity** is an Ed25519 key with a certificate signed by the authority whose subject
  names the agent (CN) and its role (OU: robot, control, cli ...). It travels as one PEM bundle:
  the private key, the certificate and the authority's certificate (`erni keys issue DIR NAME`).
- **Revocation** is an X.509 CRL signed by the authority, numbered: a newer one replaces an
  older one, and agents pass it on to the peers they talk to (`erni keys revoke DIR NAME`).

Validity dates are deliberately not checked: a robot may boot with a wrong clock, and a
certificate is trusted until revoked (they are issued from 1970 to 9999, RFC 5280's "no
well-defined expiration"). Every file is standard: `openssl verify -CAfile authority.crt`
checks a certificate, `openssl crl -CAfile authority.crt` a revocation list.
"""

from __future__ import annotations

import datetime
import hashlib
import os
import re
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.x509.oid import NameOID

from erni.blackboard.clock import wall
from erni.blackboard.errors import ConfigError
from erni.blackboard.text import NAME as NAME_PATTERN

ROLE_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,31}\Z")
AUTHORITY_KEY, AUTHORITY_CERT, REVOKED = "authority.key", "authority.crt", "revoked.crl"
ISSUED = "issued"  # DIR/issued/NAME-SERIAL.crt: every certificate the authority signed
_BEGIN = datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)
_END = datetime.datetime(9999, 12, 31, 23, 59, 59, tzinfo=datetime.UTC)


# what cryptography's lazy X.509 parser may raise on bad DER (found by fuzzing: KeyError, InvalidVersion)
_MALFORMED = (ValueError, TypeError, KeyError, IndexError, OverflowError, x509.InvalidVersion,
              x509.DuplicateExtension, x509.UnsupportedGeneralNameType)

# A certificate whose serial number is not positive (RFC 5280 forbids it) is refused as
# malformed, as cryptography will itself refuse it: its warning is raised as an error, once for
# the process (a filter set per call would not be thread-safe).
warnings.filterwarnings("error", message="Parsed a serial number which wasn't positive", category=UserWarning)
_BAD_SERIAL = "certificate is malformed: its serial number is not positive (RFC 5280)"


class IdentityError(ConfigError):
    """A key, certificate or revocation list is missing, unreadable or not of this team."""


@dataclass(frozen=True)
class Certified:
    """What a verified certificate says: the agent's name and role, its serial, its public key."""

    name: str
    role: str
    serial: int
    key: Ed25519PublicKey


def _attr(name: x509.Name, oid: x509.ObjectIdentifier) -> str:
    found = name.get_attributes_for_oid(oid)
    value = found[0].value if found else ""
    return value if isinstance(value, str) else value.decode("utf-8", "replace")


def _crl_number(crl: x509.CertificateRevocationList) -> int:
    try:
        return int(crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number)
    except x509.ExtensionNotFound:
        return 0


class Trust:
    """The authority's certificate and the newest revocation list: checks peers' certificates."""

    def __init__(self, authority: x509.Certificate, crl: x509.CertificateRevocationList | None = None):
        key = authority.public_key()
        if not isinstance(key, Ed25519PublicKey):
            raise IdentityError("the authority certificate does not hold an Ed25519 key")
        self.authority = authority
        self.authority_key = key
        self.fingerprint = hashlib.sha256(authority.public_bytes(serialization.Encoding.DER)).hexdigest()[:16]
        self._lock = threading.Lock()
        self._cache: dict[bytes, Certified] = {}
        self.revoked: frozenset[int] = frozenset()
        self.crl_number = 0
        self.crl_der = b""
        if crl is not None and not self.adopt(crl.public_bytes(serialization.Encoding.DER)):
            raise IdentityError("the revocation list is not signed by this team's authority")

    def check(self, der: bytes) -> Certified:
        """Return what a certificate of this team says; raise IdentityError if it is not one, or revoked."""
        digest = hashlib.sha256(der).digest()
        known = self._cache.get(digest)
        if known is None:
            known = self._verify(der)
            with self._lock:
                if len(self._cache) > 4096:
                    self._cache.clear()
                self._cache[digest] = known
        if known.serial in self.revoked:
            raise IdentityError(f"certificate {known.serial:x} of {known.name} is revoked")
        return known

    def _verify(self, der: bytes) -> Certified:
        try:
            return self._read(der)
        except IdentityError:
            raise
        except _MALFORMED:  # cryptography parses lazily: a bad field surfaces here, even as KeyError
            raise IdentityError("certificate is malformed") from None
        except UserWarning:  # the serial number above
            raise IdentityError(_BAD_SERIAL) from None

    def _read(self, der: bytes) -> Certified:
        try:
            cert = x509.load_der_x509_certificate(der)
            cert.verify_directly_issued_by(self.authority)
        except (ValueError, TypeError, InvalidSignature):
            raise IdentityError("certificate not signed by this team's authority") from None
        if cert.serial_number <= 0:  # where another warning filter came first
            raise IdentityError(_BAD_SERIAL)
        key = cert.public_key()
        if not isinstance(key, Ed25519PublicKey):
            raise IdentityError("certificate does not hold an Ed25519 key")
        try:
            if cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca:
                raise IdentityError("a CA certificate is not an agent identity")
        except x509.ExtensionNotFound:
            pass
        name, role = _attr(cert.subject, NameOID.COMMON_NAME), _attr(cert.subject, NameOID.ORGANIZATIONAL_UNIT_NAME)
        if not NAME_PATTERN.match(name) or not ROLE_PATTERN.match(role):
            raise IdentityError("certificate names no valid agent name and role")
        return Certified(name, role, cert.serial_number, key)

    def adopt(self, der: bytes) -> bool:
        """Take a revocation list if it is the authority's and newer than ours; return True if taken."""
        try:
            crl = x509.load_der_x509_crl(der)
            if crl.issuer != self.authority.subject or not crl.is_signature_valid(self.authority_key):
                return False
            number = _crl_number(crl)
            revoked = frozenset(r.serial_number for r in crl)
        except (*_MALFORMED, UserWarning):  # cryptography parses lazily: a bad field surfaces here, even as KeyError
            return False
        if self.crl_der and number <= self.crl_number:
            return False
        with self._lock:
            self.revoked = revoked
            self.crl_number, self.crl_der = number, der
        return True


@dataclass
class Identity:
    """This agent's key and certificate, and the team's trust."""

    name: str
    role: str
    serial: int
    key: Ed25519PrivateKey
    cert_der: bytes
    trust: Trust

    def sign(self, data: bytes) -> bytes:
        """Ed25519 signature of `data` (64 bytes)."""
        return self.key.sign(data)


def load_identity(path: str | Path, revocations: str | Path | None = None) -> Identity:
    """Read a PEM bundle (key, certificate, authority certificate); raise IdentityError naming the problem."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IdentityError(f"{path}: cannot read the identity: {err.strerror or err}") from None
    try:
        key = serialization.load_pem_private_key(data, password=None)
        certs = x509.load_pem_x509_certificates(data)
    except (ValueError, TypeError) as err:
        raise IdentityError(f"{path}: not an identity bundle (PEM key and certificates): "
                            f"{str(err).splitlines()[0]}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise IdentityError(f"{path}: the private key is not an Ed25519 key")
    if len(certs) < 2:
        raise IdentityError(f"{path}: expected the agent's certificate and the authority's certificate")
    crl = read_crl(revocations) if revocations and Path(revocations).exists() else None  # none yet: learned later
    trust = Trust(certs[-1], crl)
    der = certs[0].public_bytes(serialization.Encoding.DER)
    try:
        mine = trust.check(der)
    except IdentityError as err:
        raise IdentityError(f"{path}: {err}") from None
    if mine.key.public_bytes_raw() != key.public_key().public_bytes_raw():
        raise IdentityError(f"{path}: the private key does not belong to the certificate")
    return Identity(mine.name, mine.role, mine.serial, key, der, trust)


def read_crl(path: str | Path) -> x509.CertificateRevocationList:
    """Read a revocation list (PEM or DER); raise IdentityError naming the problem."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IdentityError(f"{path}: cannot read the revocation list: {err.strerror or err}") from None
    try:
        return x509.load_pem_x509_crl(data) if data.lstrip().startswith(b"-----") else x509.load_der_x509_crl(data)
    except ValueError:
        raise IdentityError(f"{path}: not an X.509 revocation list") from None


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")


def write_private(path: Path, data: bytes) -> None:
    """Write a secret file readable by its owner only, replacing it atomically."""
    tmp = _tmp(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def write_public(path: Path, data: bytes) -> None:
    """Write a file atomically (readers never see half of it)."""
    tmp = _tmp(path)
    tmp.write_bytes(data)
    os.replace(tmp, path)


# -- the authority (used by `erni keys` and `erni sim`) ---------------------------------------


class Authority:
    """A team authority kept in a directory: its key, its certificate, what it issued and revoked."""

    def __init__(self, directory: str | Path):
        self.dir = Path(directory)
        key_path, cert_path = self.dir / AUTHORITY_KEY, self.dir / AUTHORITY_CERT
        try:
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
            self.cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        except FileNotFoundError as err:
            raise IdentityError(f"{self.dir}: no team authority here ({Path(str(err.filename)).name} "
                                "missing); create one with `erni keys init DIR`") from None
        except (OSError, ValueError) as err:
            raise IdentityError(f"{self.dir}: cannot read the team authority: {str(err).splitlines()[0]}") from None
        if not isinstance(key, Ed25519PrivateKey):
            raise IdentityError(f"{key_path}: not an Ed25519 key")
        self.key = key

    @classmethod
    def create(cls, directory: str | Path, team: str = "ERNI team") -> Authority:
        """Make a new authority in `directory` (refuses to overwrite one)."""
        path = Path(directory)
        if (path / AUTHORITY_KEY).exists():
            raise IdentityError(f"{path}: a team authority exists already; refusing to replace it")
        path.mkdir(parents=True, exist_ok=True)
        key = Ed25519PrivateKey.generate()
        subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, team),
                             x509.NameAttribute(NameOID.COMMON_NAME, f"{team} authority")])
        cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject)
                .public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(_BEGIN).not_valid_after(_END)
                .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                             key_encipherment=False, data_encipherment=False,
                                             key_agreement=False, key_cert_sign=True, crl_sign=True,
                                             encipher_only=False, decipher_only=False), critical=True)
                .sign(key, None))
        write_private(path / AUTHORITY_KEY, key.private_bytes(serialization.Encoding.PEM,
                                                              serialization.PrivateFormat.PKCS8,
                                                              serialization.NoEncryption()))
        write_public(path / AUTHORITY_CERT, cert.public_bytes(serialization.Encoding.PEM))
        authority = cls(path)
        authority.write_crl(set(), 1)
        return authority

    def issue(self, name: str, role: str, out: str | Path | None = None) -> Path:
        """Make a key and certificate for agent `name` in `role`; write its bundle; return the path."""
        if not NAME_PATTERN.match(name):
            raise IdentityError(f"agent name {name!r}: expected letters, digits, '_', '.', '-' (at most 63)")
        if not ROLE_PATTERN.match(role):
            raise IdentityError(f"role {role!r}: expected a lower-case word such as robot, control or cli")
        key = Ed25519PrivateKey.generate()
        subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME,
                                                _attr(self.cert.subject, NameOID.ORGANIZATION_NAME) or "ERNI team"),
                             x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role),
                             x509.NameAttribute(NameOID.COMMON_NAME, name)])
        cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(self.cert.subject)
                .public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(_BEGIN).not_valid_after(_END)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False,
                                             key_encipherment=False, data_encipherment=False,
                                             key_agreement=False, key_cert_sign=False, crl_sign=False,
                                             encipher_only=False, decipher_only=False), critical=True)
                .sign(self.key, None))
        pem = cert.public_bytes(serialization.Encoding.PEM)
        issued = self.dir / ISSUED
        issued.mkdir(exist_ok=True)
        write_public(issued / f"{name}-{cert.serial_number:x}.crt", pem)
        path = Path(out) if out else self.dir / f"{name}.pem"
        write_private(path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                              serialization.NoEncryption())
                      + pem + self.cert.public_bytes(serialization.Encoding.PEM))
        return path

    def issued(self) -> list[tuple[str, str, int]]:
        """Every certificate this authority issued: (name, role, serial), oldest first."""
        found = []
        for path in sorted((self.dir / ISSUED).glob("*.crt"), key=lambda p: p.stat().st_mtime):
            try:
                cert = x509.load_pem_x509_certificate(path.read_bytes())
            except ValueError:
                continue
            found.append((_attr(cert.subject, NameOID.COMMON_NAME),
                          _attr(cert.subject, NameOID.ORGANIZATIONAL_UNIT_NAME), cert.serial_number))
        return found

    def crl(self) -> x509.CertificateRevocationList:
        """The current revocation list."""
        return read_crl(self.dir / REVOKED)

    def crl_number(self) -> int:
        """The number of the current revocation list (each revocation adds one)."""
        return _crl_number(self.crl())

    def revoke(self, name_or_serial: str) -> list[int]:
        """Revoke every certificate issued to an agent name (or one serial, in hex); return the serials."""
        crl = self.crl()
        revoked = {r.serial_number for r in crl}
        serials = [serial for name, _, serial in self.issued() if name == name_or_serial]
        if not serials:
            try:
                serials = [int(name_or_serial, 16)]
            except ValueError:
                raise IdentityError(f"{self.dir}: no certificate was issued to {name_or_serial!r}") from None
        new = [s for s in serials if s not in revoked]
        if new:
            self.write_crl(revoked | set(new), _crl_number(crl) + 1)
        return new

    def write_crl(self, serials: set[int], number: int) -> Path:
        """Sign and write a revocation list with these serials and this number."""
        now = datetime.datetime.fromtimestamp(wall(), datetime.UTC)
        builder = (x509.CertificateRevocationListBuilder().issuer_name(self.cert.subject)
                   .last_update(now).next_update(_END).add_extension(x509.CRLNumber(number), critical=False))
        for serial in sorted(serials):
            builder = builder.add_revoked_certificate(
                x509.RevokedCertificateBuilder().serial_number(serial).revocation_date(now).build())
        path = self.dir / REVOKED
        write_public(path, builder.sign(self.key, None).public_bytes(serialization.Encoding.PEM))
        return path
