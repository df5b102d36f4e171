"""The real-mesh tier's machinery: namespaces, radio rules in the kernel, babeld, clean-up after a kill.

Traffic here flows only between namespaces these tests make; each test removes what it made.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from erni.blackboard.testing import wait_until
from erni.sim import netns
from erni.sim.netns import Mesh

pytestmark = pytest.mark.netns


def in_ns(mesh: Mesh, name: str, code: str, timeout: float = 30.0) -> str:
    """Run Python `code` inside node `name`'s namespace; return its stdout."""
    done = subprocess.run(mesh.exec_argv(name, [sys.executable, "-c", textwrap.dedent(code)]),
                          capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done.stdout


RECEIVE = """
    import socket
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("", 47999)); s.settimeout(1.5); n = 0
    print("ready", flush=True)
    try:
        while True:
            s.recv(64); n += 1
    except socket.timeout:
        print(n)
"""


def test_the_radio_drops_out_of_range_frames_and_thins_a_lossy_link_in_the_kernel(tmp_path):
    mesh = Mesh(["a", "b", "c"], tmp_path).create()
    try:
        # a - b loss-free, b - c at half delivery, a - c out of range
        mesh.apply({frozenset(("a", "b")): 1.0, frozenset(("b", "c")): 0.5})
        receivers = {n: subprocess.Popen(mesh.exec_argv(n, [sys.executable, "-c", textwrap.dedent(RECEIVE)]),
                                         stdout=subprocess.PIPE, text=True) for n in ("a", "c")}
        for proc in receivers.values():
            assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        in_ns(mesh, "b", f"""
            import socket, time
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            for i in range(400):
                s.sendto(b"x", ("{mesh.broadcast}", 47999))
                time.sleep(0.001)
        """)
        got = {n: int(proc.communicate(timeout=10)[0].split()[-1]) for n, proc in receivers.items()}
        assert got["a"] == 400
        assert 140 < got["c"] < 260  # binomial(400, 0.5): far outside 6 sigma otherwise
        dropped, passed = mesh.counters()[("b", "c")]  # the kernel's counts (IPv6 chatter of the links too)
        assert passed >= got["c"] and dropped >= 400 - got["c"] and dropped + passed < 440
        assert ("a", "c") not in mesh.counters()  # no rule: the chain's policy drops everything
        unicast = in_ns(mesh, "a", f"""
            import socket
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM); s.settimeout(2)
            try:
                s.connect(("{mesh.node('c').address}", 9)); print("connected")
            except OSError as err:
                print(type(err).__name__)
        """)
        assert "connected" not in unicast  # out of range and no routing daemon: nothing gets through
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []


def test_babeld_routes_around_a_gap_and_the_babel_source_reads_the_kernels_routes(tmp_path):
    mesh = Mesh(["a", "b", "c"], tmp_path).create()
    try:
        mesh.apply({frozenset(("a", "b")): 1.0, frozenset(("b", "c")): 1.0})  # a line: a cannot hear c
        mesh.start_babel()
        c = mesh.node("c").address
        wait_until(lambda: any(r.startswith(f"{c} via {mesh.node('b').address}") for r in mesh.kernel_routes("a")),
                   timeout=20)
        names = {mesh.node(n).address: n for n in "bc"}
        out = in_ns(mesh, "a", f"""
            import asyncio, json
            from erni.plugins.mobinet.babel import BabelSource
            from erni.plugins.mobinet.resource import PARTS
            async def main():
                source = BabelSource("::1", {mesh.babel_port}, node="a", names=lambda: {names!r})
                try:
                    for _ in range(100):  # until the far link's cost has settled (its first IHUs)
                        view = await source.read(PARTS)
                        if [r.cost for r in view.routes if r.destination == "c"] == [2.0]:
                            break
                        await asyncio.sleep(0.1)
                finally:
                    await source.aclose()
                print(json.dumps({{"routes": {{r.destination: [r.next_hop, r.cost] for r in view.routes}},
                                  "neighbours": {{n.name: n.quality for n in view.neighbors}},
                                  "links": sorted(sorted((l.a, l.b)) for l in view.links),
                                  "source": view.sources["routes"]}}))
            asyncio.run(main())
        """)
        view = json.loads(out)
        kernel = {line.split()[0]: line.split()[2] for line in mesh.kernel_routes("a")}
        assert {dest: hop for dest, (hop, _) in view["routes"].items()} == {
            names[d]: names[h] for d, h in kernel.items()}
        assert view["routes"]["c"] == ["b", 2.0] and view["neighbours"] == {"b": 1.0}
        assert ["a", "b"] in view["links"] and ["b", "c"] in view["links"]
        assert "babel [::1]" in view["source"]
        assert sorted(mesh.daemons_alive()) == ["a", "b", "c"]
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []


LAUNCHER = """
    import sys, time
    from erni.sim.netns import Mesh
    mesh = Mesh(["x", "y"], sys.argv[1]).create()
    mesh.start_babel()
    print(mesh.tag, flush=True)
    time.sleep(120)
"""


def test_a_killed_launcher_leaves_namespaces_that_the_next_start_removes(tmp_path):
    launcher = subprocess.Popen([sys.executable, "-c", textwrap.dedent(LAUNCHER), str(tmp_path / "dead")],
                                stdout=subprocess.PIPE, text=True)
    assert launcher.stdout is not None
    tag = launcher.stdout.readline().strip()
    assert len(tag) == 4, tag
    os.kill(launcher.pid, signal.SIGKILL)
    launcher.wait(10)
    left = [n for n in netns._namespaces() if n.startswith(f"erni-{tag}")]
    assert sorted(left) == [f"erni-{tag}", f"erni-{tag}-x", f"erni-{tag}-y"]
    # its babeld children die with it (they would otherwise keep routing in the orphaned namespaces)
    wait_until(lambda: all(not netns._ip("netns", "pids", n, check=False).split() for n in left), timeout=10)
    mesh = Mesh(["z"], tmp_path / "next")
    try:
        mesh.create()  # the next start recognises the dead owner and removes its run
        assert not [n for n in netns._namespaces() if n.startswith(f"erni-{tag}")]
        assert not (netns.STATE_DIR / f"{tag}.json").exists()
        assert not [line for line in netns._ip("-o", "link", "show").splitlines() if f"erni{tag}m" in line]
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []


def test_a_live_run_is_never_taken_for_a_dead_one(tmp_path):
    first = Mesh(["p"], tmp_path / "one").create()
    try:
        assert netns.clean_stale() == []
        second = Mesh(["q"], tmp_path / "two").create()  # another run side by side: its own slot and subnets
        try:
            assert first.slot != second.slot and first.subnet != second.subnet
            assert first.leftovers() and second.leftovers()  # both still exist
        finally:
            second.destroy()
    finally:
        first.destroy()
    assert first.leftovers() == [] and second.leftovers() == []


def test_a_run_whose_record_cannot_be_read_is_kept_not_guessed_dead(tmp_path, caplog):
    """Clean-up removes only what it can prove dead: a damaged record names no owner to check, so its
    namespaces stay (with a warning) until the record is mended or removed by hand."""
    mesh = Mesh(["r"], tmp_path).create()
    record = netns.STATE_DIR / f"{mesh.tag}.json"
    good = record.read_text()
    try:
        record.write_text(good[: len(good) // 2])  # a torn write: not JSON
        assert netns.clean_stale() == []
        assert f"erni-{mesh.tag}-r" in netns._namespaces()
        assert f"keeping run {mesh.tag}" in caplog.text
        record.write_text(good)
    finally:
        mesh.destroy()
    assert mesh.leftovers() == []
