"""MobiNet reads Debian's net-snmp agent (`snmpd`) over SNMPv3, USM authPriv (HMAC-SHA-2, AES-128),
and a wrong key is refused in one line that names what to check."""

from __future__ import annotations

import asyncio
import os
import subprocess
from collections.abc import Iterator

import pytest

from erni.blackboard import Agent, NetInfo, Task
from erni.blackboard.errors import ConfigError
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.resource import PARTS, ROUTES, SourceError
from erni.plugins.mobinet.snmp import SnmpSource
from erni.plugins.mobinet.usm import UsmUser
from tests.mobinet.test_snmpd import SNMPD, _free_udp_port, kernel_routes

pytestmark = pytest.mark.skipif(SNMPD is None, reason="Debian package 'snmpd' not installed")
HOSTNAME = "erni-snmpd-v3"
AUTH, PRIV = "erni auth passphrase", "erni priv passphrase"
USERS = {"erni": "SHA-256", "erni512": "SHA-512"}


def _snmpget_v3(port: int, user: str, auth: str, priv: str, protocol: str = "SHA-256") -> str:
    res = subprocess.run(["snmpget", "-v3", "-l", "authPriv", "-u", user, "-a", protocol, "-A", auth, "-x", "AES",
                          "-X", priv, "-On", "-m", "", "-t", "1", "-r", "0", f"udp:127.0.0.1:{port}",
                          "1.3.6.1.2.1.1.5.0"], capture_output=True, text=True, timeout=30)
    return res.stdout + res.stderr


@pytest.fixture(scope="module")
def snmpd_v3(tmp_path_factory) -> Iterator[int]:
    """snmpd on a loopback port that knows only USM users (no community), authPriv required."""
    work = tmp_path_factory.mktemp("snmpd-v3")
    port = _free_udp_port()
    users = "".join(f'createUser {u} {a} "{AUTH}" AES "{PRIV}"\nrouser {u} priv\n' for u, a in USERS.items())
    (work / "snmpd.conf").write_text(f"{users}sysName {HOSTNAME}\n")
    (work / "state").mkdir()
    env = {**os.environ, "MIBS": "", "SNMP_PERSISTENT_DIR": str(work / "state"), "SNMPCONFPATH": str(work)}
    proc = subprocess.Popen([SNMPD, "-f", "-C", "-c", str(work / "snmpd.conf"), "-Lf", str(work / "log"),
                             "-p", str(work / "pid"), "-I", "-smux", f"udp:127.0.0.1:{port}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def up() -> bool:
        async def ask() -> bool:
            src = SnmpSource("127.0.0.1", port, timeout=0.5, usm=UsmUser("erni", AUTH, PRIV))
            try:
                await src.get([(1, 3, 6, 1, 2, 1, 1, 5, 0)])
                return True
            except SourceError:
                return False
            finally:
                await src.aclose()
        return proc.poll() is not None or asyncio.run(ask())

    try:
        wait_until(up, timeout=20)
        if proc.poll() is not None:
            pytest.fail(f"snmpd exited: {(work / 'log').read_text(errors='replace')}")
        yield port
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def read(port: int, user: UsmUser, parts: frozenset[str] = PARTS, timeout: float = 1.0) -> object:
    async def go() -> object:
        src = SnmpSource("127.0.0.1", port, timeout=timeout, usm=user)
        try:
            return await src.read(parts)
        except SourceError as err:
            return err
        finally:
            await src.aclose()
    return asyncio.run(go())


@pytest.mark.parametrize("name", USERS)
def test_the_client_reads_snmpd_over_snmpv3_authpriv(snmpd_v3, name):
    view = read(snmpd_v3, UsmUser(name, AUTH, PRIV, auth_protocol=USERS[name]))
    assert not isinstance(view, Exception), view
    assert view.node == HOSTNAME
    assert {(r.destination, r.next_hop, r.cost) for r in view.routes if ":" not in r.destination} == kernel_routes()
    assert view.sources[ROUTES].startswith(f"snmp 127.0.0.1:{snmpd_v3} IP-FORWARD-MIB inetCidrRouteTable")


def test_snmpd_refuses_v2c_here(snmpd_v3):
    """The agent of these tests serves no community: what was read above came over SNMPv3."""
    async def go() -> object:
        src = SnmpSource("127.0.0.1", snmpd_v3, timeout=0.3)
        try:
            return await src.read(frozenset({ROUTES}))
        except SourceError as err:
            return err
        finally:
            await src.aclose()
    assert "no SNMP response received before timeout" in str(asyncio.run(go()))


def test_a_wrong_auth_key_is_refused_in_one_line(snmpd_v3):
    err = read(snmpd_v3, UsmUser("erni", "not the auth passphrase", PRIV))
    assert isinstance(err, SourceError)
    assert str(err) == (f"SNMPv3 GET to 127.0.0.1:{snmpd_v3} as 'erni': authentication failed "
                        "(usmStatsWrongDigests): wrong auth key or auth protocol for user 'erni'")
    assert "authentication failure" in _snmpget_v3(snmpd_v3, "erni", "not the auth passphrase", PRIV).lower()


def test_a_wrong_auth_protocol_or_user_is_refused_in_one_line(snmpd_v3):
    err = read(snmpd_v3, UsmUser("erni", AUTH, PRIV, auth_protocol="SHA-384"))
    assert "authentication failed (usmStatsWrongDigests)" in str(err) and "\n" not in str(err)
    err = read(snmpd_v3, UsmUser("nobody", AUTH, PRIV))
    assert str(err).endswith("no SNMPv3 user 'nobody' there (usmStatsUnknownUserNames)")


def test_a_wrong_priv_key_times_out_naming_the_priv_key(snmpd_v3):
    """snmpd drops a request it cannot decrypt (AES decrypts to garbage, not to an error): it says nothing."""
    err = read(snmpd_v3, UsmUser("erni", AUTH, "not the priv passphrase"), timeout=0.5)
    assert isinstance(err, SourceError)
    assert "no SNMP response received before timeout" in str(err) and "wrong priv key" in str(err)
    assert "\n" not in str(err)


def test_mobinet_watches_snmpd_over_snmpv3_with_keys_from_a_file_and_the_environment(snmpd_v3, tmp_path,
                                                                                     monkeypatch, caplog):
    keyfile = tmp_path / "auth.key"
    keyfile.write_text(AUTH + "\n")
    keyfile.chmod(0o600)
    monkeypatch.setenv("ERNI_TEST_PRIV", PRIV)
    agent = Agent("host", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"host": "127.0.0.1", "port": snmpd_v3, "timeout": 1.0, "v3_user": "erni",
                               "auth_protocol": "SHA-256", "auth_key_file": str(keyfile),
                               "priv_key_env": "ERNI_TEST_PRIV", "write_pose": False})
    agent.start()
    try:
        task = Task(verb="NetWatch", preposition="path_cost", params={"rate_hz": 5}, source="test")
        with agent.transaction() as tx:
            tx.add(task)
        info: NetInfo = wait_until(lambda: next((i for i in agent.query(NetInfo)
                                                 if i.task == task.uid and i.provenance), None), timeout=15)
    finally:
        agent.stop()
    assert not info.degraded and info.node == HOSTNAME
    assert {(r.destination, r.next_hop, r.cost) for r in info.routes if ":" not in r.destination} == kernel_routes()
    assert PRIV not in caplog.text and AUTH not in caplog.text


def test_mobinet_degrades_a_watch_with_a_wrong_key_in_one_line(snmpd_v3):
    agent = Agent("host", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"host": "127.0.0.1", "port": snmpd_v3, "timeout": 1.0, "v3_user": "erni",
                               "auth_key": "not the auth passphrase", "priv_key": PRIV, "write_pose": False})
    agent.start()
    try:
        task = Task(verb="NetWatch", preposition="path_cost", params={"rate_hz": 5}, source="test")
        with agent.transaction() as tx:
            tx.add(task)
        info: NetInfo = wait_until(lambda: next((i for i in agent.query(NetInfo)
                                                 if i.task == task.uid and "usm" in i.message), None), timeout=15)
    finally:
        agent.stop()
    assert info.degraded
    assert info.message == (f"SNMPv3 GET to 127.0.0.1:{snmpd_v3} as 'erni': authentication failed "
                            "(usmStatsWrongDigests): wrong auth key or auth protocol for user 'erni'")


def test_v3_settings_are_checked_before_the_agent_starts(tmp_path, monkeypatch):
    def settings(**extra: object) -> None:
        Agent("host").add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                                 settings={"v3_user": "erni", **extra})
    monkeypatch.delenv("ERNI_TEST_NOT_SET", raising=False)
    with pytest.raises(ConfigError, match="environment variable ERNI_TEST_NOT_SET is not set"):
        settings(auth_key_env="ERNI_TEST_NOT_SET", priv_key=PRIV)
    with pytest.raises(ConfigError, match="expected exactly one of auth_key, auth_key_file, auth_key_env"):
        settings(auth_key=AUTH, auth_key_env="X", priv_key=PRIV)
    loose = tmp_path / "loose.key"
    loose.write_text(AUTH)
    loose.chmod(0o644)
    with pytest.raises(ConfigError, match="readable by others"):
        settings(auth_key_file=str(loose), priv_key=PRIV)
    with pytest.raises(ConfigError, match="at least 8"):
        settings(auth_key="short", priv_key=PRIV)
    with pytest.raises(ConfigError, match="remove write_community"):
        settings(auth_key=AUTH, priv_key=PRIV, write_community="private")
    with pytest.raises(ConfigError, match="auth_protocol"):
        settings(auth_key=AUTH, priv_key=PRIV, auth_protocol="MD5")
    with pytest.raises(ConfigError, match="v3_user is not"):
        Agent("host").add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                                 settings={"priv_key": PRIV})
