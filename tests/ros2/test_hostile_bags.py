"""Bags handed to the operator that are built to hurt: a decompression bomb (a few kilobytes on disk,
hundreds of megabytes in a chunk), a chunk that holds more than it declares, a message beyond the
bound, Odometry with NaN, a topic that names a terminal escape instead of a robot. Each is refused
(the whole bag, for a bomb) or skipped (one message or topic) with one line, and `erni replay`
stays within bounded memory.

The bombs are written here record by record (MCAP's framing), around the schema and channel records
of a real bag that `rosbags` writes.
"""

from __future__ import annotations

import json
import math
import struct
import sys
from pathlib import Path

import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from erni import mcap_bounds
from erni import ros2_messages as ros
from erni.bags import read_bag
from erni.blackboard import Pose
from erni.replay import LogError, read_log

JAZZY = get_typestore(Stores.ROS2_JAZZY)
ODOMETRY = "nav_msgs/msg/Odometry"
MB = 1024 * 1024

if sys.version_info >= (3, 14):
    from compression import zstd
else:
    from backports import zstd


def odometry(robot: str, x: float, y: float = 0.0, stamp: float = 1_700_000_000.0) -> bytes:
    pose = Pose.model_construct(robot="r", x=x, y=y, theta=0.0, v=0.0, w=0.0)  # a bag's numbers, unchecked
    return ros.serialize(ros.odometry(pose, int(stamp * 1e9)))


def real_bag(path: Path, topics: dict[str, list[bytes]]) -> Path:
    """A bag rosbags writes (zstd chunks): Odometry messages on the given topics, one second apart."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode

    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    for topic, datas in topics.items():
        conn = writer.add_connection(topic, ODOMETRY, typestore=JAZZY)
        for i, data in enumerate(datas):
            writer.write(conn, (1_700_000_000 + i) * 10**9, data)
    writer.close()
    return path / f"{path.name}.mcap"


def records(data: bytes) -> list[tuple[int, bytes]]:
    """An MCAP file's top-level records: (opcode, content)."""
    out, i = [], len(mcap_bounds.MAGIC)
    while i + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, i)
        out.append((op, data[i + 9:i + 9 + length]))
        if op == mcap_bounds.FOOTER:
            break
        i += 9 + length
    return out


def record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


def message_record(channel: int, data_size: int) -> tuple[bytes, int]:
    """The head of a message record whose data is `data_size` zero bytes (written by the caller), and its size."""
    head = struct.pack("<BQHIQQ", 0x05, 22 + data_size, channel, 0, 1_700_000_000 * 10**9, 1_700_000_000 * 10**9)
    return head, len(head) + data_size


def bomb(path: Path, tmp: Path, zeros: int, declared: int | None = None) -> Path:
    """An MCAP file of a real bag's header, schema and channel, then one zstd chunk holding one
    Odometry message of `zeros` zero bytes (compressed as a stream: the test never holds them),
    declaring its true size or `declared`; no summary (readers scan it)."""
    template = real_bag(tmp / f"template-{path.stem}", {"/robot1/odom": [odometry("robot1", 1.0)]}).read_bytes()
    kept = b"".join(record(op, content) for op, content in records(template) if op in (0x01, 0x03, 0x04))
    channel = next(struct.unpack_from("<H", content)[0] for op, content in records(template) if op == 0x04)
    head, size = message_record(channel, zeros)
    compressor = zstd.ZstdCompressor()
    packed = [compressor.compress(head)]
    block = bytes(MB)
    for _ in range(zeros // MB):
        packed.append(compressor.compress(block))
    packed.append(compressor.compress(bytes(zeros % MB)))
    packed.append(compressor.flush())
    compressed = b"".join(packed)
    chunk = struct.pack("<QQQI", 1_700_000_000 * 10**9, 1_700_000_000 * 10**9, size if declared is None else declared, 0)
    chunk += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(compressed)) + compressed
    footer = record(mcap_bounds.FOOTER, struct.pack("<QQI", 0, 0, 0))
    path.write_bytes(mcap_bounds.MAGIC + kept + record(0x06, chunk) + record(0x0F, struct.pack("<I", 0)) + footer
                     + mcap_bounds.MAGIC)
    return path


def replay_peak(path: Path) -> tuple[int, str, int]:
    """`erni replay PATH` in a process of its own: its exit code, stderr, and how far its peak memory
    (KiB) rose beyond what its imports took."""
    from tests.reliability.test_record_replay import replay_memory

    out, grown = replay_memory(path)
    lines = out.stderr.strip().splitlines()
    return out.returncode, "\n".join(lines[:-1]), grown


def test_a_bomb_of_one_300_mb_message_is_refused_in_one_line_within_bounded_memory(tmp_path):
    """24 KB on disk, one 300 MB message inside: `erni replay` refuses it by the chunk's declared size
    before decompressing anything (it reached 1.93 GB), and as much when the chunk declares 1 KB."""
    honest = bomb(tmp_path / "honest.mcap", tmp_path, 300 * MB)
    assert honest.stat().st_size < 100_000
    code, err, peak = replay_peak(honest)
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "the chunk at byte" in err and f"decompresses to {300 * MB + 31} bytes; expected at most {mcap_bounds.MAX_CHUNK}" in err
    assert 0 <= peak < 40 * 1024, f"grew by {peak} KiB"
    liar = bomb(tmp_path / "liar.mcap", tmp_path, 300 * MB, declared=1000)
    code, err, peak = replay_peak(liar)
    assert code == 2 and "holds more than the 1000 bytes it declares" in err and len(err.splitlines()) == 1, err
    assert 0 <= peak < 40 * 1024, f"grew by {peak} KiB"


def test_a_message_beyond_the_bound_is_refused_in_a_chunk_and_alone(tmp_path):
    big = bomb(tmp_path / "big.mcap", tmp_path, 3 * MB)
    with pytest.raises(LogError, match=rf"a message of {3 * MB + 22} bytes at byte 0 of the chunk; expected at most {2 * MB}"):
        read_bag(big, max_message=2 * MB)
    with pytest.raises(LogError, match=rf"decompresses to {3 * MB + 31} bytes; expected at most {MB}"):
        read_bag(big, max_chunk=MB)
    _, events, problems = read_bag(big)  # within the defaults: read (its one message is no Odometry)
    assert events == [] and len(problems) == 1


def test_a_good_bag_is_read_as_before_the_bounds(tmp_path):
    path = real_bag(tmp_path / "good", {"/robot1/odom": [odometry("robot1", float(i)) for i in range(50)]})
    mcap_bounds.check(path)  # no exception
    _, events, problems = read_bag(path)
    assert problems == [] and [e.obj.x for e in events] == [float(i) for i in range(50)]  # type: ignore[attr-defined]


def test_odometry_with_nan_or_infinity_is_skipped_and_named_and_the_rest_replays(tmp_path):
    path = real_bag(tmp_path / "nan", {"/robot1/odom": [odometry("robot1", 1.0), odometry("robot1", math.nan),
                                                         odometry("robot1", 2.0, math.inf), odometry("robot1", 3.0)]})
    _, events, problems = read_log(path)
    assert [e.obj.x for e in events] == [1.0, 3.0]  # type: ignore[attr-defined]
    assert len(problems) == 2 and all("/robot1/odom" in p and "finite number" in p for p in problems), problems


def test_a_topic_that_names_no_robot_is_skipped_and_named_escaped(tmp_path):
    hostile = "/r\x1b[2J\x1b]0;owned\x07/odom"
    path = real_bag(tmp_path / "names", {hostile: [odometry("x", 1.0)], "/robot1/odom": [odometry("robot1", 2.0)]})
    _, events, problems = read_log(path)
    assert {e.obj.robot for e in events} == {"robot1"}  # type: ignore[attr-defined]
    assert len(problems) == 1 and "\x1b" not in problems[0] and "\\x1b[2J" in problems[0], problems
    code, err, _ = replay_peak(path)
    assert code == 0 and "\x1b" not in err and "skipping" in err, err


def test_an_erni_status_naming_an_agent_with_escapes_is_skipped(tmp_path):
    from erni.bags import BagRecorder

    out = tmp_path / "agents.mcap"
    recorder = BagRecorder(out, "127.0.0.1:1", started=1_700_000_000.0)
    good = Pose(robot="robot1", x=1.0)
    recorder.write("control", "add", "Pose", good.model_dump(mode="json"), t=0.0)
    recorder.write("ctl\x1b[2J", "change", "Pose", good.model_dump(mode="json"), t=0.5)
    recorder.write("control", "change", "Pose", {**good.model_dump(mode="json"), "x": math.nan}, t=1.0)
    recorder.close()
    _, events, problems = read_log(out)
    assert [e.agent for e in events] == ["control"]
    assert len(problems) == 2 and "'ctl\\x1b[2J': expected a name" in problems[0] and "finite" in problems[1], problems
    assert json.dumps(problems)  # plain text


def test_a_bag_of_no_erni_topic_is_refused_in_one_line_its_topics_escaped(tmp_path):
    # found by the MCAP bags fuzzer: the refusal listed the bag's topics raw, so a topic holding a
    # newline made it two lines
    bag = real_bag(tmp_path / "b", {"/robot1\n/odom": [odometry("robot1", 1.0)], "/r\x1b[2J/odom": [odometry("r", 1.0)]})
    with pytest.raises(LogError) as err:
        read_log(bag)
    assert "no ERNI topics" in str(err.value)
    assert "\n" not in str(err.value) and "\x1b" not in str(err.value)
    assert "/robot1\\n/odom" in str(err.value) and "/r\\x1b[2J/odom" in str(err.value)


def test_an_lz4_chunk_that_holds_more_than_it_declares_is_refused(tmp_path):
    """lz4 chunks (rosbag2's other MCAP compression) are walked as zstd ones are: read when honest,
    refused in one line when a chunk holds more than it declares."""
    from erni.bags import BagRecorder

    out = tmp_path / "lz4.mcap"
    recorder = BagRecorder(out, "127.0.0.1:1", started=1_700_000_000.0, compression="lz4")
    for i in range(200):
        recorder.write("control", "change", "Pose", Pose(robot="robot1", x=float(i)).model_dump(mode="json"), t=i / 10)
    recorder.close()
    assert [e.obj.x for e in read_log(out)[1]] == [float(i) for i in range(200)]  # type: ignore[attr-defined]
    data = bytearray(out.read_bytes())
    at = data.index(b"\x03\x00\x00\x00lz4") - 9 - 28  # the first chunk: start, end, size, crc, then "lz4"
    assert data[at] == 0x06
    struct.pack_into("<QI", data, at + 9 + 16, 1000, 0)  # its declared uncompressed size (and no CRC to check)
    liar = tmp_path / "liar.mcap"
    liar.write_bytes(bytes(data))
    with pytest.raises(LogError, match="holds more than the 1000 bytes it declares"):
        read_log(liar)


def test_a_single_robots_bag_with_nan_odometry_or_a_hostile_robot_name(tmp_path):
    """A robot's own bag (Odometry on /odom) replayed with --robot: a NaN message is skipped and named;
    a --robot that is no name is refused in one line, its escapes shown escaped."""
    path = real_bag(tmp_path / "own", {"/odom": [odometry("x", 1.0), odometry("x", math.nan), odometry("x", 2.0)]})
    _, events, problems = read_log(path, robot="tb3")
    assert [(e.obj.robot, e.obj.x) for e in events] == [("tb3", 1.0), ("tb3", 2.0)]  # type: ignore[attr-defined]
    assert len(problems) == 1 and "/odom" in problems[0] and "finite number" in problems[0], problems
    with pytest.raises(LogError) as err:
        read_log(path, robot="r\x1b[2J")
    assert "\x1b" not in str(err.value) and "\\x1b[2J" in str(err.value) and "\n" not in str(err.value)
    # beside a namespaced robot's odometry, /odom without --robot is skipped and named; the rest replays
    both = real_bag(tmp_path / "both", {"/odom": [odometry("x", 1.0)], "/robot1/odom": [odometry("robot1", 2.0)]})
    _, events, problems = read_log(both)
    assert [(e.obj.robot, e.obj.x) for e in events] == [("robot1", 2.0)]  # type: ignore[attr-defined]
    assert len(problems) == 1 and "/odom" in problems[0] and "--robot NAME" in problems[0], problems
