"""`erni keys`, and its files checked by OpenSSL's command-line tools as an independent reader."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
OPENSSL = shutil.which("openssl")


def erni(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "erni", "keys", *args], capture_output=True, text=True,
                          timeout=30, cwd=ROOT)


def openssl(*args: str, data: bytes | None = None) -> subprocess.CompletedProcess[bytes]:
    assert OPENSSL, "openssl is installed by .ci/run"
    return subprocess.run([OPENSSL, *args], capture_output=True, timeout=30, input=data)


@pytest.fixture
def keys(tmp_path):
    d = tmp_path / "keys"
    out = erni("init", str(d), "--team", "test team")
    assert out.returncode == 0 and "team authority 'test team'" in out.stdout
    return d


def test_init_issue_revoke_list_show(keys):
    for name, role in (("robot1", "robot"), ("control", "control"), ("operator", "cli")):
        out = erni("issue", str(keys), name, "--role", role)
        assert out.returncode == 0 and f"{name} ({role})" in out.stdout, out.stderr
    for secret in (keys / "authority.key", keys / "robot1.pem"):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600, f"{secret} is readable by others"
    out = erni("revoke", str(keys), "robot1")
    assert out.returncode == 0 and "list 2" in out.stdout
    assert "already revoked" in erni("revoke", str(keys), "robot1").stdout
    listing = erni("list", str(keys)).stdout.splitlines()
    assert [ln.split()[0] for ln in listing] == ["robot1", "control", "operator"]
    assert listing[0].endswith("REVOKED") and not listing[1].endswith("REVOKED")
    out = erni("show", str(keys / "control.pem"), "--revocations", str(keys / "revoked.crl"))
    assert out.returncode == 0 and "control (control)" in out.stdout and "revocation list 2" in out.stdout
    assert "PRIVATE" not in out.stdout
    out = erni("show", str(keys / "robot1.pem"), "--revocations", str(keys / "revoked.crl"))
    assert out.returncode == 2 and "is revoked" in out.stderr


def test_mistakes_are_one_line(keys, tmp_path):
    for args, message in (
        (("init", str(keys)), "a team authority exists already"),
        (("issue", str(keys), "no spaces"), "agent name 'no spaces'"),
        (("issue", str(keys), "r1", "--role", "Robot!"), "role 'Robot!'"),
        (("issue", str(tmp_path / "nowhere"), "r1"), "no team authority here"),
        (("revoke", str(keys), "ghost"), "no certificate was issued to 'ghost'"),
        (("show", str(tmp_path / "nothing.pem")), "cannot read the identity"),
    ):
        out = erni(*args)
        assert out.returncode == 2, args
        (line,) = out.stderr.strip().splitlines()
        assert message in line and "Traceback" not in out.stderr


def test_openssl_reads_and_verifies_every_file(keys):
    erni("issue", str(keys), "robot1")
    erni("issue", str(keys), "robot2")
    erni("revoke", str(keys), "robot2")
    issued = sorted((keys / "issued").glob("*.crt"))
    out = openssl("verify", "-CAfile", str(keys / "authority.crt"), *map(str, issued))
    assert out.returncode == 0 and out.stdout.count(b": OK") == 2, out
    out = openssl("crl", "-in", str(keys / "revoked.crl"), "-CAfile", str(keys / "authority.crt"), "-noout",
                  "-text")
    assert out.returncode == 0 and b"verify OK" in out.stderr + out.stdout
    serial = re.search(rb"Serial Number: ([0-9A-F]+)", out.stdout).group(1).decode().lstrip("0").lower()
    robot2 = next(p for p in issued if p.name.startswith("robot2-"))
    assert robot2.stem.split("-")[1].lstrip("0") == serial
    subject = openssl("x509", "-in", str(keys / "robot1.pem"), "-noout", "-subject").stdout
    assert b"OU = robot" in subject and b"CN = robot1" in subject
    from_key = openssl("pkey", "-in", str(keys / "robot1.pem"), "-pubout").stdout
    from_cert = openssl("x509", "-in", str(keys / "robot1.pem"), "-pubkey", "-noout").stdout
    assert from_key and from_key == from_cert, "the bundle's key belongs to its certificate"


def test_a_handshake_signature_verifies_with_openssl(keys, tmp_path):
    """Ed25519 as OpenSSL knows it: the signature on a handshake frame, over DOMAIN + frame."""
    from erni.transport.identity import load_identity
    from erni.transport.session import DOMAIN, IdentityAuth, cut_signed, initiate

    erni("issue", str(keys), "robot1")
    auth = IdentityAuth(load_identity(keys / "robot1.pem"))
    frame = initiate(auth, "0" * 32, ("127.0.0.1", 1), ("127.0.0.1", 2), "control").frame
    signed = cut_signed(frame, 65536)
    (tmp_path / "data").write_bytes(DOMAIN + signed.signed)
    (tmp_path / "sig").write_bytes(signed.proof)
    pub = tmp_path / "pub.pem"
    pub.write_bytes(openssl("x509", "-in", str(keys / "robot1.pem"), "-pubkey", "-noout").stdout)
    ok = openssl("pkeyutl", "-verify", "-pubin", "-inkey", str(pub), "-rawin", "-in", str(tmp_path / "data"),
                 "-sigfile", str(tmp_path / "sig"))
    assert ok.returncode == 0 and b"Signature Verified Successfully" in ok.stdout
    (tmp_path / "data").write_bytes(DOMAIN + signed.signed + b"x")
    bad = openssl("pkeyutl", "-verify", "-pubin", "-inkey", str(pub), "-rawin", "-in", str(tmp_path / "data"),
                  "-sigfile", str(tmp_path / "sig"))
    assert bad.returncode != 0
    assert os.path.getsize(tmp_path / "sig") == 64


def test_a_certificate_with_a_serial_number_that_is_not_positive_is_refused_as_malformed():
    """RFC 5280: a serial number is positive. A certificate from the wire with a negative one is
    refused with a one-line reason (cryptography only warns about it today)."""
    import warnings

    from erni.transport.identity import IdentityError, load_identity
    from tests.transport.helpers import identity

    ident = load_identity(identity("serial-test"))
    der = bytearray(ident.cert_der)
    def header(i: int) -> int:  # DER: tag, then a short or long form length
        return 2 if der[i + 1] < 0x80 else 2 + (der[i + 1] & 0x7F)

    # Certificate SEQUENCE, tbsCertificate SEQUENCE, [0] version (5 bytes), then the serial
    tbs = header(0)
    at = tbs + header(tbs) + 5
    assert der[at] == 0x02, "the serial INTEGER follows the version"
    der[at + 2] |= 0x80  # its first content byte: the number turns negative
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing may merely warn
        with pytest.raises(IdentityError, match="serial number is not positive"):
            ident.trust.check(bytes(der))
        assert ident.trust.check(ident.cert_der).name == "serial-test"
