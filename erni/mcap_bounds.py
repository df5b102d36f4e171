"""An MCAP file's records held to bounds before a reader decompresses them.

A bag from elsewhere may be a bomb: a chunk a few kilobytes long on disk that decompresses to
hundreds of megabytes, or that holds more than it declares. `rosbags` decompresses a whole chunk
at once, whatever its size, so `check` walks the file first, record by record, and decompresses
each chunk as a stream, never holding more than a block of it:

| bound | default | what |
|---|---|---|
| `MAX_CHUNK` | 32 MiB | a chunk's decompressed size, as declared and as found |
| `MAX_MESSAGE` | 16 MiB | one message record (in a chunk or not) |

A bag beyond them is refused as a whole, with one line naming the record, its offset and the
bound; a bag within them costs one more pass of decompression.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path
from typing import Any, BinaryIO

from erni.blackboard.errors import ErniError

MAX_CHUNK = 32 * 1024 * 1024
MAX_MESSAGE = 16 * 1024 * 1024
MAGIC = b"\x89MCAP0\r\n"
BLOCK = 1 << 20  # bytes read from the file, and decompressed, at a time
_RECORD = struct.Struct("<BQ")  # opcode, length
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start time, end time, uncompressed size, uncompressed crc
_U32, _U64 = struct.Struct("<I"), struct.Struct("<Q")
FOOTER, MESSAGE, CHUNK = 0x02, 0x05, 0x06


class BagBoundError(ErniError):
    """An MCAP file breaks a bound (`MAX_CHUNK`, `MAX_MESSAGE`) or its records do not add up."""


def _decompressor(compression: str) -> Any:
    if compression == "zstd":
        if sys.version_info >= (3, 14):
            from compression import zstd  # type: ignore[import-not-found,unused-ignore]
        else:
            from backports import zstd  # type: ignore[import-not-found,unused-ignore]
        return zstd.ZstdDecompressor()
    if compression == "lz4":
        from lz4.frame import LZ4FrameDecompressor  # type: ignore[import-untyped,unused-ignore]

        return LZ4FrameDecompressor()
    return None


class _Messages:
    """Follows the records of a chunk's decompressed bytes as they come, checking each message's length."""

    def __init__(self, where: str, max_message: int):
        self.where, self.max_message = where, max_message
        self.head = b""
        self.skip = 0
        self.offset = 0

    def feed(self, data: bytes) -> None:
        view, i = memoryview(data), 0
        while i < len(view):
            if self.skip:
                step = min(self.skip, len(view) - i)
                self.skip -= step
                i += step
                continue
            take = min(_RECORD.size - len(self.head), len(view) - i)
            self.head += bytes(view[i:i + take])
            i += take
            if len(self.head) == _RECORD.size:
                op, length = _RECORD.unpack(self.head)
                if op == MESSAGE and length > self.max_message:
                    raise BagBoundError(f"{self.where}: a message of {length} bytes at byte {self.offset + i - 9} of "
                                        f"the chunk; expected at most {self.max_message}")
                self.head, self.skip = b"", length
        self.offset += len(view)


def check(path: Path, max_chunk: int = MAX_CHUNK, max_message: int = MAX_MESSAGE) -> None:
    """Walk an MCAP file's records; raise BagBoundError at the first beyond a bound. A file whose
    records are cut short or damaged is left to the reader (it names that); only sizes are judged."""
    with path.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            return
        while True:
            start = f.tell()
            head = f.read(_RECORD.size)
            if len(head) < _RECORD.size:
                return
            op, length = _RECORD.unpack(head)
            if op == FOOTER:
                return
            if op == MESSAGE and length > max_message:
                raise BagBoundError(f"{path}: a message of {length} bytes at byte {start}; expected at most {max_message}")
            if op == CHUNK:
                _check_chunk(f, f"{path}: the chunk at byte {start}", length, max_chunk, max_message)
            f.seek(start + _RECORD.size + length)


def _check_chunk(f: BinaryIO, where: str, length: int, max_chunk: int, max_message: int) -> None:
    fixed = f.read(_CHUNK_HEAD.size + _U32.size)
    if len(fixed) < _CHUNK_HEAD.size + _U32.size:
        return
    _, _, size, _ = _CHUNK_HEAD.unpack_from(fixed)
    if size > max_chunk:
        raise BagBoundError(f"{where}: decompresses to {size} bytes; expected at most {max_chunk}")
    (name_length,) = _U32.unpack_from(fixed, _CHUNK_HEAD.size)
    if name_length > 64:
        raise BagBoundError(f"{where}: a compression name of {name_length} bytes")
    compression = f.read(name_length).decode("ascii", "replace")
    raw = f.read(_U64.size)
    if len(raw) < _U64.size:
        return
    (left,) = _U64.unpack(raw)
    if left > length:
        raise BagBoundError(f"{where}: {left} compressed bytes in a record of {length}")
    messages = _Messages(where, max_message)
    decompressor = _decompressor(compression)
    found = 0
    pending = b""
    while True:
        if decompressor is None:  # stored as it is (or a compression the reader will name)
            if compression not in ("", "none"):
                return
            out = f.read(min(BLOCK, left))
            left -= len(out)
            if not out:
                break
        else:
            if decompressor.eof:  # a frame ended: what follows is another frame (or nothing)
                pending = (decompressor.unused_data or b"") + pending  # lz4 says None for none
                if not pending and not left:
                    break
                decompressor = _decompressor(compression)
            if decompressor.needs_input and not pending:
                if not left:
                    break
                pending = f.read(min(BLOCK, left))
                left -= len(pending)
                if not pending:
                    break
            try:
                out = decompressor.decompress(pending, max_length=BLOCK)
            except Exception:  # noqa: BLE001  # damaged data: the reader names it
                return
            pending = b""
        found += len(out)
        if found > size:
            raise BagBoundError(f"{where}: holds more than the {size} bytes it declares")
        messages.feed(out)
