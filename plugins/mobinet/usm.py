"""SNMPv3 with the User-based Security Model (RFC 3414) for MobiNet, through pysnmp: authPriv only.

Authentication is HMAC-SHA-2 (RFC 7860: SHA-224, SHA-256, SHA-384, SHA-512), privacy AES-128
(RFC 3826, net-snmp's `-x AES`). Key localisation, digests and encryption are pysnmp's own (its
USM encrypts through the `cryptography` package and hashes through hashlib); ERNI only hands the
keys over. pysnmp is imported when a v3
user is configured, never before: a robot agent speaking v2c does not load it.

`UsmUser` is one user and its keys (`read_key` takes a key from the config, a file or an
environment variable); `V3Session` sends MobiNet's GET, GETBULK and SET requests as that user
and returns the answer in `ber`'s plain values, so `SnmpSource` decodes v2c and v3 answers alike.
"""

from __future__ import annotations

import asyncio
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from erni.blackboard.errors import ConfigError
from erni.plugins.mobinet import ber
from erni.plugins.mobinet.ber import Value
from erni.plugins.mobinet.resource import SourceError

OID = tuple[int, ...]

# the names net-snmp's tools take (`-a SHA-256 -x AES`) -> pysnmp's protocol constants
AUTH_PROTOCOLS = {"SHA-224": "usmHMAC128SHA224AuthProtocol", "SHA-256": "usmHMAC192SHA256AuthProtocol",
                  "SHA-384": "usmHMAC256SHA384AuthProtocol", "SHA-512": "usmHMAC384SHA512AuthProtocol"}
PRIV_PROTOCOLS = {"AES": "usmAesCfb128Protocol"}
MIN_KEY = 8   # RFC 3414 11.2: a passphrase of at least 8 octets


@dataclass(frozen=True)
class UsmUser:
    """An SNMPv3 USM user with its authentication and privacy passphrases (never shown in a repr)."""

    name: str
    auth_key: str = field(repr=False)
    priv_key: str = field(repr=False)
    auth_protocol: str = "SHA-256"
    priv_protocol: str = "AES"

    def __post_init__(self) -> None:
        if not 1 <= len(self.name) <= 32:
            raise ConfigError(f"SNMPv3 user name {self.name!r}: expected 1..32 characters (RFC 3414)")
        if self.auth_protocol not in AUTH_PROTOCOLS:
            raise ConfigError(f"SNMPv3 user {self.name!r}: auth protocol {self.auth_protocol!r}: expected one of "
                              f"{', '.join(AUTH_PROTOCOLS)}")
        if self.priv_protocol not in PRIV_PROTOCOLS:
            raise ConfigError(f"SNMPv3 user {self.name!r}: priv protocol {self.priv_protocol!r}: expected one of "
                              f"{', '.join(PRIV_PROTOCOLS)}")
        for what, key in (("auth", self.auth_key), ("priv", self.priv_key)):
            if len(key.encode()) < MIN_KEY:
                raise ConfigError(f"SNMPv3 user {self.name!r}: the {what} key has {len(key.encode())} byte(s); "
                                  f"expected at least {MIN_KEY} (RFC 3414)")

    def hlapi_user(self) -> Any:
        """pysnmp's `UsmUserData` for this user (passphrases: pysnmp localises them to each agent)."""
        from pysnmp.hlapi.v3arch import asyncio as hl

        return hl.UsmUserData(self.name, self.auth_key, self.priv_key,
                              authProtocol=getattr(hl, AUTH_PROTOCOLS[self.auth_protocol]),
                              privProtocol=getattr(hl, PRIV_PROTOCOLS[self.priv_protocol]))


def read_key(what: str, value: str | None = None, file: str | None = None, env: str | None = None) -> str:
    """One key from exactly one of: the value itself, the first line of a file, an environment variable.

    `what` names the setting in errors (`auth_key`); a file others may read is refused."""
    given = [kind for kind, v in (("", value), ("_file", file), ("_env", env)) if v is not None]
    if len(given) != 1:
        raise ConfigError(f"{what}: expected exactly one of {what}, {what}_file, {what}_env; got "
                          f"{', '.join(what + k for k in given) or 'none'}")
    if value is not None:
        return value
    if env is not None:
        key = os.environ.get(env)
        if not key:
            raise ConfigError(f"{what}: environment variable {env} is not set or empty")
        return key
    assert file is not None
    path = Path(file).expanduser()
    try:
        mode = path.stat().st_mode
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise ConfigError(f"{what}: {file}: {err.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"{what}: {file}: readable by others (mode {stat.S_IMODE(mode):o}); "
                          f"expected 600 (chmod 600 {file})")
    if not lines or not lines[0]:
        raise ConfigError(f"{what}: {file}: the first line is empty; expected the key")
    return lines[0]


# --- the client ------------------------------------------------------------------------

# what an agent's USM Report means, in the words of the setting to fix
_REFUSALS = {
    "WrongDigest": "authentication failed (usmStatsWrongDigests): wrong auth key or auth protocol for user {user!r}",
    "UnknownUserName": "no SNMPv3 user {user!r} there (usmStatsUnknownUserNames)",
    "UnsupportedSecurityLevel": "user {user!r} may not use authPriv there (usmStatsUnsupportedSecLevels): "
                                "check the agent's user and priv protocol",
    "DecryptionError": "the agent could not decrypt the request (usmStatsDecryptionErrors): wrong priv key or "
                       "priv protocol for user {user!r}",
    "NotInTimeWindow": "the request was outside the agent's time window (usmStatsNotInTimeWindows)",
    "UnknownEngineID": "the agent does not know the engine ID used (usmStatsUnknownEngineIDs)",
}
_UNSIGNED = {ber.COUNTER32, ber.GAUGE32, ber.TIME_TICKS, ber.COUNTER64}


def value_of(obj: Any) -> Value:
    """A pysnmp/pyasn1 value as `ber.Value` (the tag its BER encoding would carry); BerError if unknown."""
    tag = obj.tagSet[-1]
    code = tag.tagClass | tag.tagFormat | tag.tagId
    if code in ber.EXCEPTIONS or code == ber.NULL:
        return Value(code, None)
    if code == ber.INTEGER or code in _UNSIGNED:
        return Value(code, int(obj))
    if code in (ber.OCTET_STRING, ber.IP_ADDRESS, ber.OPAQUE):
        return Value(code, bytes(obj.asOctets()))
    if code == ber.OBJECT_IDENTIFIER:
        return Value(code, tuple(obj))
    raise ber.BerError(f"unknown value type 0x{code:02x}")


def _pysnmp_value(value: Value) -> Any:
    from pysnmp.proto import rfc1902

    if value.tag == ber.NULL:
        return rfc1902.Null("")
    if value.tag == ber.INTEGER and isinstance(value.value, int):
        return rfc1902.Integer32(value.value)
    raise ber.BerError(f"MobiNet sends no {value.type_name} over SNMPv3")


def _line(err: BaseException) -> str:
    """The first line of an exception's text."""
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class V3Session:
    """Requests to one agent as one USM user, authPriv; pysnmp's engine lives on the calling loop."""

    def __init__(self, host: str, port: int, user: UsmUser, timeout: float, retries: int) -> None:
        self.host, self.port, self.user = host, port, user
        self.timeout, self.retries = timeout, retries
        self._engine: Any = None
        self._target: Any = None
        self._auth: Any = None
        self._opening = asyncio.Lock()   # a pose write and a read may both be the first request

    @property
    def where(self) -> str:
        """`host:port` of the agent."""
        return f"{self.host}:{self.port}"

    async def _open(self) -> None:
        from pysnmp.hlapi.v3arch import asyncio as hl

        async with self._opening:
            if self._engine is not None:
                return
            kind = hl.Udp6TransportTarget if ":" in self.host else hl.UdpTransportTarget
            try:
                self._target = await kind.create((self.host, self.port), timeout=self.timeout, retries=self.retries)
            except Exception as err:   # pysnmp wraps resolver errors in its own exception
                raise SourceError(f"SNMPv3 agent {self.where}: cannot resolve: {_line(err)}") from None
            self._auth = self.user.hlapi_user()
            self._engine = hl.SnmpEngine()

    async def request(self, what: str, pdu: int, varbinds: list[tuple[OID, Value]],
                      max_repetitions: int = 0) -> ber.Response:
        """Send one request and return the answer; SourceError (one line) for no answer or a refusal."""
        from pysnmp.hlapi.v3arch import asyncio as hl
        from pysnmp.proto.rfc1902 import ObjectName

        await self._open()
        binds = [hl.ObjectType(hl.ObjectIdentity(ObjectName(oid)), _pysnmp_value(v)) for oid, v in varbinds]
        head = (self._engine, self._auth, self._target, hl.ContextData())
        if pdu == ber.GET:
            call = hl.get_cmd(*head, *binds, lookupMib=False)
        elif pdu == ber.GET_BULK:
            call = hl.bulk_cmd(*head, 0, max_repetitions, *binds, lookupMib=False)
        elif pdu == ber.SET:
            call = hl.set_cmd(*head, *binds, lookupMib=False)
        else:
            raise ber.BerError(f"not a request MobiNet sends: 0x{pdu:02x}")
        try:
            indication, status, index, answer = await call
        except Exception as err:   # e.g. a socket error while sending: one line, as every SourceError
            raise SourceError(f"SNMPv3 {what} to {self.where}: {type(err).__name__}: {_line(err)}") from None
        if indication:
            raise SourceError(f"SNMPv3 {what} to {self.where} as {self.user.name!r}: {self.explain(indication)}")
        try:
            got = [(tuple(name), value_of(value)) for name, value in answer]
        except ber.BerError as err:
            raise SourceError(f"SNMPv3 {what} to {self.where}: {err}") from None
        return ber.Response(3, b"", 0, int(status), int(index), got)

    def explain(self, indication: Any) -> str:
        """pysnmp's error indication as the reason and the setting to check."""
        name = type(indication).__name__
        if name in _REFUSALS:
            return _REFUSALS[name].format(user=self.user.name)
        if name == "RequestTimedOut":
            tries = f"{self.retries} retr{'y' if self.retries == 1 else 'ies'}"
            return (f"no SNMP response received before timeout (timeout {self.timeout:g} s, {tries}); an agent "
                    "that cannot decrypt a request (wrong priv key) stays silent too")
        return str(indication)

    async def aclose(self) -> None:
        """Close pysnmp's sockets."""
        engine, self._engine = self._engine, None
        if engine is not None:
            engine.close_dispatcher()
