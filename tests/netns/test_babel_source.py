"""BabelSource: babeld 1.12.1's own dumps (pinned vectors) turned into neighbours, routes and topology.

The vectors in `vectors/` were captured from Debian's babeld in four namespaces with known radio
rules (see vectors/README.md); the routes babeld installed in each kernel at that moment are
the independent check of the routes the source reports.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from erni.plugins.mobinet.babel import BabelSource, build_view, parse_dump, quality
from erni.plugins.mobinet.resource import NEIGHBORS, PARTS, POSITIONS, ROUTES, TOPOLOGY, SourceError
from erni.plugins.mobinet.snmp import articulation_points

VECTORS = Path(__file__).parent / "vectors"
ADDRESS = {"a": "10.231.0.1", "b": "10.231.0.2", "c": "10.231.0.3", "d": "10.231.0.4"}
NAMES = {address: name for name, address in ADDRESS.items()}
KERNEL = {  # `ip route show proto babel` in each namespace when the dumps were taken: destination -> via
    "a": {"b": "b", "c": "b", "d": "b"},
    "b": {"a": "a", "c": "d", "d": "d"},
    "c": {"a": "d", "b": "d", "d": "d"},
    "d": {"a": "b", "b": "b", "c": "c"},
}
WHERE = "babel [::1]:33123"


def dump_of(node: str) -> list[str]:
    return (VECTORS / f"babeld-1.12.1-{node}.txt").read_text().splitlines()


def view_of(node: str, parts: frozenset[str] = PARTS):
    names = {a: n for a, n in NAMES.items() if n != node}
    return build_view(parse_dump(dump_of(node)), parts, node=node, where=WHERE, names=names)


def test_the_header_and_every_line_of_a_real_dump_are_read():
    dump = parse_dump(dump_of("b"))
    assert dump.version == "babeld-1.12.1" and dump.my_id == "48:de:c4:a5:d8:81:f4:2f"
    assert [i.ipv4 for i in dump.interfaces] == ["10.231.0.2"]
    assert len(dump.neighbours) == 3 and len(dump.routes) == 9
    assert dump.xroutes == [("10.231.0.2/32", 0)]
    lossy = next(n for n in dump.neighbours if n.cost == 563)
    assert (lossy.rxcost, lossy.txcost, lossy.reach) == (383, 376, 0xD57F)


@pytest.mark.parametrize("node", "abcd")
def test_installed_routes_are_the_kernels_routes(node):
    view = view_of(node, frozenset({ROUTES}))
    got = {r.destination: r.next_hop for r in view.routes}
    assert got == KERNEL[node]
    for r in view.routes:
        assert r.hops == (1 if r.next_hop == r.destination else 0)
    costs = {r.destination: r.cost for r in view.routes}
    if node == "a":  # a - b - d - c: three loss-free hops of 256 each
        assert costs == {"b": 1.0, "d": 2.0, "c": 3.0}


def test_neighbours_are_named_by_the_prefix_they_originate_and_the_quality_follows_the_costs():
    view = view_of("b", frozenset({NEIGHBORS}))
    by_name = {n.name: n for n in view.neighbors}
    assert set(by_name) == {"a", "c", "d"}
    assert by_name["a"].address == "10.231.0.1" and by_name["a"].quality == 1.0
    lossy = by_name["c"]
    assert lossy.metric == 563 and lossy.symmetric
    assert lossy.quality == pytest.approx(256 / math.sqrt(383 * 376))
    # the radio dropped 30 % each way: a delivery ratio of 0.7, which babeld's Hellos estimate
    assert abs(lossy.quality - 0.7) < 0.1
    # the newest Hellos alone (reach d57f: 1101 01.. of the last six, newest first) and a clean link's
    assert lossy.recent == pytest.approx(4 / 6) and by_name["a"].recent == 1.0
    assert "neighbour table" in view.sources[NEIGHBORS] and WHERE in view.sources[NEIGHBORS]


def test_an_unnamed_address_keeps_its_address_and_own_addresses_name_this_node():
    dump = parse_dump(dump_of("a"))
    view = build_view(dump, PARTS, node="a", where=WHERE, names={})
    assert {r.destination for r in view.routes} == {"10.231.0.2", "10.231.0.3", "10.231.0.4"}
    assert view.address == "10.231.0.1" and view.names["10.231.0.1"] == "a"


@pytest.mark.parametrize("node, cut", [("a", False), ("b", True), ("c", False), ("d", True)])
def test_each_node_knows_whether_it_is_an_articulation_point(node, cut):
    """b holds a to the rest: a cut vertex. c is not: b reaches d directly. d is reported as one
    although the lossy b - c link goes around it: b's and c's best routes to each other both run
    through d (512 < 563 and 640), so nothing in d's daemon shows that link. The source errs on
    the side of caution there, which for the network-aware stop means holding still."""
    view = view_of(node, frozenset({TOPOLOGY}))
    assert (node in articulation_points(view.links)) is cut
    own = {frozenset((l.a, l.b)) for l in view.links if node in (l.a, l.b)}
    assert own == {frozenset((node, n.name)) for n in view_of(node, frozenset({NEIGHBORS})).neighbors}


def test_a_neighbour_whose_paths_run_through_this_node_gets_no_edge():
    """b's neighbours a and d both reach each other only through b: no a - d edge in b's view."""
    links = {frozenset((l.a, l.b)) for l in view_of("b", frozenset({TOPOLOGY})).links}
    assert frozenset(("a", "d")) not in links and frozenset(("a", "c")) not in links
    assert frozenset(("c", "d")) in links


def test_positions_are_missing_with_the_reason_and_writing_one_is_refused():
    view = view_of("a", frozenset({POSITIONS}))
    assert "no positions" in view.missing[POSITIONS] and not view.positions


def test_quality_of_costs():
    assert quality(256, 256) == 1.0
    assert quality(512, 512) == 0.5
    assert quality(0xFFFF, 256) == 0.0 and quality(256, 0xFFFF) == 0.0
    assert quality(96, 96) == 1.0  # a wired interface's cost: capped at 1


@pytest.mark.parametrize("line, expected", [
    ("add neighbour 1 address fe80::1 if mesh0 reach ffff ureach 0000 rxcost 256 txcost x cost 256",
     "txcost 'x'"),
    ("add neighbour 1 address nowhere if mesh0 reach ffff rxcost 256 txcost 256 cost 256", "address 'nowhere'"),
    ("add neighbour 1 address fe80::1 if mesh0 reach ffff rxcost 256 cost 256", "lacks 'txcost'"),
    ("add route 1 prefix 10.0.0.1/32 from 0.0.0.0/0 installed maybe id x metric 1 refmetric 0 via fe80::1 if m",
     "installed 'maybe'"),
    ("add route 1 prefix 10.0.0.1/99 installed yes id x metric 1 refmetric 0 via fe80::1 if m", "prefix"),
    ("add route 1 prefix 10.0.0.1/32 installed yes id x metric 70000 refmetric 0 via fe80::1 if m", "0..65535"),
    ("add interface mesh0 up true ipv4", "KEY VALUE"),
])
def test_a_malformed_line_is_one_clear_error(line, expected):
    with pytest.raises(SourceError) as err:
        parse_dump([line])
    assert expected in str(err.value) and "\n" not in str(err.value)


def test_unknown_kinds_and_fields_of_newer_versions_are_ignored():
    dump = parse_dump(["add neighbour 1 address fe80::1 if mesh0 reach ffff ureach 0000 rxcost 256 txcost 256 "
                       "rtt 1.5 rttcost 0 cost 256 newfield 7", "add gadget 1 colour blue", "something else"])
    assert len(dump.neighbours) == 1


WORDS = st.sampled_from(["add", "neighbour", "route", "xroute", "interface", "address", "fe80::1", "10.0.0.1/32",
                         "rxcost", "txcost", "cost", "256", "65535", "-1", "ffff", "yes", "no", "true", "via",
                         "if", "mesh0", "prefix", "metric", "refmetric", "installed", "id", "up", "ipv4", "reach"])


@given(st.lists(st.one_of(st.lists(WORDS, max_size=16).map(" ".join), st.text(max_size=60)), max_size=8))
def test_any_lines_are_parsed_or_refused_with_a_source_error(lines):
    try:
        dump = parse_dump(lines)
    except SourceError:
        return
    build_view(dump, PARTS, node="me", where=WHERE)


# --- the connection: a scripted peer speaking babeld's local protocol ---------------------

class FakeBabeld:
    """Serves the header and the pinned dump of node `node`; or says `answer` to `dump`."""

    def __init__(self, node: str = "b", answer: str | None = None, header: str = "BABEL 1.0") -> None:
        lines = dump_of(node)
        split = lines.index("ok") + 1
        self.header = [header] + lines[1:split]
        self.body = lines[split:]
        self.answer = answer
        self.dumps = 0

    async def __call__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(("\n".join(self.header) + "\n").encode())
        while (line := await reader.readline()):
            if line.strip() == b"dump":
                self.dumps += 1
                writer.write(((self.answer + "\n") if self.answer else "\n".join(self.body) + "\n").encode())
            await writer.drain()
        writer.close()


def run_against(fake: FakeBabeld, reads: int = 1, parts: frozenset[str] = PARTS):
    async def go():
        server = await asyncio.start_server(fake, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        source = BabelSource("127.0.0.1", port, node="b", timeout=2.0, names=lambda: NAMES)
        try:
            return [await source.read(parts) for _ in range(reads)], source
        finally:
            await source.aclose()
            server.close()
            await server.wait_closed()
    return asyncio.run(go())


def test_one_connection_serves_every_read():
    fake = FakeBabeld()
    views, source = run_against(fake, reads=3)
    assert fake.dumps == 3 and source.requests == 3
    assert {r.destination: r.next_hop for r in views[-1].routes} == KERNEL["b"]
    assert "babeld-1.12.1" in views[0].sources["node"]


def test_a_refused_dump_and_a_stranger_are_source_errors():
    with pytest.raises(SourceError, match="answered 'no"):
        run_against(FakeBabeld(answer="no permission"))
    with pytest.raises(SourceError, match="not babeld's local interface"):
        run_against(FakeBabeld(header="SSH-2.0-OpenSSH"))


def test_nobody_listening_says_how_babeld_must_be_started():
    async def go():
        source = BabelSource("127.0.0.1", 1, node="x", timeout=1.0)
        try:
            await source.read(PARTS)
        finally:
            await source.aclose()
    with pytest.raises(SourceError, match="babeld running with -g 1"):
        asyncio.run(go())


def test_writing_a_position_is_refused():
    from erni.blackboard import Position

    with pytest.raises(SourceError, match="no positions"):
        asyncio.run(BabelSource().write_position(Position(x=0, y=0)))
