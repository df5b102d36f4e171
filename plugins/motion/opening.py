"""Opening an ARCOS link: the exchanges on a port before the link is up.

The SYNC0-SYNC2 handshake (the robot names itself), the CONFIG request (SIPs that arrive meanwhile
are handed on) and the HOSTBAUD switch to a faster serial rate. `ArcosDriver` opens each session
with a `LinkOpening`; what is written goes through the driver's writer, what is read through its
packet reader.
"""

from __future__ import annotations

import fcntl
import logging
import socket
import sys
import termios
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial

from erni.plugins.motion import arcos
from erni.plugins.motion.arcos import Cmd

log = logging.getLogger("erni.motion.driver")


@dataclass(frozen=True)
class RobotInfo:
    """What the robot said in its SYNC2 reply."""

    name: str = ""
    robot_class: str = ""
    subclass: str = ""


def waiting(port: Any) -> int:
    """Bytes the port can give without blocking.

    pyserial's `in_waiting` counts them on a serial line, but its socket:// handler (MobileSim,
    AMRISim, `erni robot-sim`) only says 0 or 1, so a reader trusting it takes a SIP a byte at a
    time (about 60 reads per SIP); for a socket the kernel's count (FIONREAD) is asked instead.
    """
    sock = getattr(port, "_socket", None)  # pyserial's socket handler keeps its socket here
    if isinstance(sock, socket.socket):
        try:
            return int.from_bytes(fcntl.ioctl(sock.fileno(), termios.FIONREAD, bytes(4)), sys.byteorder, signed=True)
        except OSError:
            pass
    return int(port.in_waiting)


def _sync_reply(sync: int) -> Callable[[bytes], bool]:
    """Whether a packet body is the reply to SYNC`sync` (SYNC0/1 echo one byte; SYNC2 names the robot)."""
    return lambda body: body[0] == sync and (sync == 2 or len(body) == 1)


class LinkOpening:
    """One session's opening exchanges on `port`: each written through `write` (the driver's writer,
    open during the handshake), each answer read through `reader`; `stop` cuts every wait short.
    `last_error` says why a handshake failed."""

    def __init__(self, url: str, port: serial.SerialBase, reader: arcos.PacketReader,
                 write: Callable[[bytes], bool], stop: threading.Event, clock: Callable[[], float]) -> None:
        self.url = url
        self.port = port
        self.reader = reader
        self.write = write
        self.stop = stop
        self.clock = clock
        self.last_error = ""

    def handshake(self, attempts: int, timeout: float) -> RobotInfo | None:
        """SYNC0, SYNC1, SYNC2, each answered within `timeout` s, up to `attempts` times; the robot's
        SYNC2 reply, or None."""
        for attempt in range(attempts):
            if self.stop.is_set():
                return None
            if attempt:
                self.write(arcos.encode_command(Cmd.CLOSE))
                self.stop.wait(0.05)
            self.port.reset_input_buffer()
            self.reader.reset()
            reply: bytes | None = None
            for sync in (0, 1, 2):
                self.write(arcos.encode_command(sync))
                reply = self.wait_for(_sync_reply(sync), timeout)
                if reply is None:
                    self.last_error = f"no SYNC{sync} reply (attempt {attempt + 1}/{attempts})"
                    break
            else:
                assert reply is not None  # the loop ran to its end: SYNC2 answered
                return RobotInfo(*arcos.parse_sync2(reply))
        return None

    def request_config(self, timeout: float, other: Callable[[bytes], None]) -> arcos.RobotConfig | None:
        """Send CONFIG and wait `timeout` s for the reply, handing the packets that arrive meanwhile (SIPs)
        to `other`."""
        if timeout <= 0:
            return None
        self.write(arcos.encode_command(Cmd.CONFIG, 1))
        reply = self.wait_for(lambda b: b[0] == arcos.CONFIG_REPLY, timeout, other)
        if reply is None:
            return None
        try:
            return arcos.parse_config(reply)
        except arcos.ProtocolError as err:
            log.warning("%s: bad CONFIG reply: %s", self.url, err)
            return None

    def switch_baud(self, baud: int) -> None:
        """HOSTBAUD, then the same rate on our side; back to the old rate if the robot falls silent."""
        port = self.port
        code = arcos.BAUD_CODES.get(baud)
        if code is None:
            log.warning("%s: switch_baud %d is not a HOSTBAUD rate; expected one of %s", self.url, baud,
                        ", ".join(map(str, arcos.BAUD_CODES)))
            return
        old = port.baudrate
        self.write(arcos.encode_command(Cmd.HOSTBAUD, code))
        port.flush()
        self.stop.wait(0.01)
        port.baudrate = baud
        self.reader.reset()
        self.stop.wait(0.01)
        self.write(arcos.encode_command(Cmd.PULSE))
        if self.wait_for(lambda b: True, 0.9, None) is None:
            log.warning("%s: the robot did not answer at %d baud; staying at %d", self.url, baud, old)
            port.baudrate = old
            self.reader.reset()
        else:
            log.info("%s: serial line switched from %d to %d baud", self.url, old, baud)

    def wait_for(self, match: Callable[[bytes], bool], timeout: float,
                 other: Callable[[bytes], None] | None = None) -> bytes | None:
        """The first packet body `match` accepts within `timeout` s (the others to `other`), or None."""
        deadline = self.clock() + timeout
        while self.clock() < deadline and not self.stop.is_set():
            for body in self.reader.feed(self.port.read(waiting(self.port) or 1)):
                if match(body):
                    return body
                if other is not None:
                    other(body)
        return None
