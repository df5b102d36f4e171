"""`erni net-sim` as a user runs it: prints each node's SNMP address, serves, stops on Ctrl-C."""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import sys

ADDR_RE = re.compile(r"^\s+(\S+)\s+(\d+\.\d+\.\d+\.\d+)\s+snmp udp:([\d.]+):(\d+)$")


def test_net_sim_serves_every_node_until_interrupted(tmp_path):
    scenario = tmp_path / "three.toml"
    scenario.write_text(
        "comm_range = 100.0\nlossless_range = 50.0\nbase_port = 0\nwrite_community = 'w-all'\n"
        'nodes = [{name = "a", x = 0, y = 0}, {name = "b", x = 60, y = 0, write_community = "w-b"}, '
        '{name = "c", x = 120, y = 0}]\n'
        'moves = [{at = 0.2, node = "c", x = 30, y = 30}]\n')
    proc = subprocess.Popen([sys.executable, "-m", "erni", "net-sim", str(scenario)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines, addresses = [], {}
        while "serving; Ctrl-C to stop" not in lines[-1:]:
            line = proc.stdout.readline()
            assert line, f"net-sim exited early: {proc.stderr.read()}"
            lines.append(line.rstrip("\n"))
            m = ADDR_RE.match(lines[-1])
            if m:
                addresses[m.group(1)] = (m.group(2), m.group(3), int(m.group(4)))
        assert sorted(addresses) == ["a", "b", "c"]
        assert addresses["b"][0] == "10.0.0.2"
        assert "articulation points: b" in "\n".join(lines)
        move = proc.stdout.readline()
        assert "c -> (30, 30)" in move and "articulation points: none" in move
        if shutil.which("snmpget"):
            _, host, port = addresses["b"]
            out = subprocess.run(["snmpget", "-v2c", "-c", "public", "-On", "-m", "", "-t", "1",
                                  f"udp:{host}:{port}", "1.3.6.1.4.1.32473.1.1.1.0"],
                                 capture_output=True, text=True, timeout=10).stdout
            assert 'STRING: "b"' in out

            def set_x(community: str) -> str:
                res = subprocess.run(["snmpset", "-v2c", "-c", community, "-On", "-m", "", "-t", "1",
                                      "-r", "0", f"udp:{host}:{port}", "1.3.6.1.4.1.32473.1.1.4.0", "i", "5"],
                                     capture_output=True, text=True, timeout=10)
                return res.stdout + res.stderr
            assert "noAccess" in set_x("public")         # the read community never writes
            assert "Timeout" in set_x("w-all")           # b has a write community of its own
            assert "INTEGER: 5" in set_x("w-b")
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "net-sim: stopped" in out


def test_net_sim_refuses_a_write_community_equal_to_the_read_one(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('comm_range = 10\nlossless_range = 5\nwrite_community = "public"\n'
                   'nodes = [{name = "a", x = 0, y = 0}]\n')
    res = subprocess.run([sys.executable, "-m", "erni", "net-sim", str(bad)],
                         capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert "node 'a': the write community must differ from the read community 'public'" in res.stderr


def test_net_sim_rejects_a_bad_scenario(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('comm_range = 10\nlossless_range = 50\nnodes = [{name = "a", x = 0, y = 0}]\n')
    res = subprocess.run([sys.executable, "-m", "erni", "net-sim", str(bad)],
                         capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert "lossless_range (50.0 m) must not exceed comm_range (10.0 m)" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_net_sim_reports_a_busy_port(tmp_path):
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        scenario = tmp_path / "one.toml"
        scenario.write_text(f'comm_range = 10\nlossless_range = 5\nbase_port = {port}\n'
                            'nodes = [{name = "a", x = 0, y = 0}]\n')
        res = subprocess.run([sys.executable, "-m", "erni", "net-sim", str(scenario)],
                             capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert f"node 'a': cannot serve SNMP on 127.0.0.1:{port}" in res.stderr
