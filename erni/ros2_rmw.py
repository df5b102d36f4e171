"""rmw_zenoh's wire (ROS 2 Jazzy) on a Zenoh session: key expressions, liveliness tokens, attachments, QoS.

What a ROS 2 node on `RMW_IMPLEMENTATION=rmw_zenoh_cpp` expects, without ROS 2:

- a topic's data travels on `<domain>/<topic without its leading />/<DDS type name>/<RIHS01 type hash>`,
  e.g. `0/robot1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9...`, its payload CDR (little-endian,
  with the 4-byte encapsulation header);
- each sample carries an attachment: the sequence number (int64), the source time in ns (int64) and the
  publisher's 16-byte GID, in Zenoh's serialisation (little-endian integers, the GID a sequence whose
  length, 16, is one LEB128 byte);
- discovery is by liveliness tokens under `@ros2_lv/<domain>/<session zid>/<node id>/...`: one per node
  (`NN`) and one per publisher (`MP`), subscription (`MS`) or service server (`SS`), the names mangled
  ('/' written '%'), with the QoS in rmw_zenoh's compact form;
- a service is a queryable (complete) on the key expression a topic of the service's type would have;
  a request is a query whose payload is the request's CDR and whose attachment is a topic sample's
  (the client's sequence number, its time, its GID); the reply carries the response's CDR and an
  attachment with the request's sequence number and GID and the reply's time.
"""

from __future__ import annotations

import itertools
import os
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import UsageError
from erni.ros2_messages import dds_type_name, type_hash

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
RMW_ZENOH_DEFAULT_DEPTH = 42  # the depth rmw_zenoh gives a keep-last QoS of depth 0, left out of tokens


def _ns(seconds: float) -> int:
    """Seconds since the epoch as rmw_zenoh's source time (integer nanoseconds)."""
    return int(seconds * 1_000_000_000)



@dataclass(frozen=True)
class QoS:
    """The QoS rmw_zenoh writes in a liveliness token (what ROS 2 tools match publishers and subscriptions on).

    `encode()` gives rmw_zenoh's form `RELIABILITY:DURABILITY:HISTORY,DEPTH:DEADLINE:LIFESPAN:LIVELINESS`,
    each component equal to rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite
    durations, automatic liveliness) left empty: rclcpp's default profile (depth 10) is `::,10:,:,:,,`."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def encode(self) -> str:
        reliability = "" if self.reliable else "2"
        durability = "1" if self.transient_local else ""
        depth = "" if self.depth == RMW_ZENOH_DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


DEFAULT_QOS = QoS()
SENSOR_QOS = QoS(reliable=False, depth=5)  # rclcpp's SensorDataQoS


def mangle(name: str) -> str:
    """A name inside a token: '/' written '%' ('/robot1/odom' -> '%robot1%odom'; '' and '/' -> '%')."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def topic_key(domain_id: int, topic: str, typename: str) -> str:
    """The key expression of a topic's data: '0/robot1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_...'."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(typename)}/{type_hash(typename)}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness token of a node: '@ros2_lv/0/<zid>/<node id>/<node id>/NN/%/<ns>/<name>'."""
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{mangle(node)}"


def endpoint_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                   topic: str, typename: str, qos: QoS) -> str:
    """The liveliness token of a publisher (`kind` 'MP') or subscription ('MS')."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{mangle(node)}/"
            f"{mangle(topic)}/{dds_type_name(typename)}/{type_hash(typename)}/{qos.encode()}")


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """A sample's attachment as rmw_zenoh writes and reads it."""
    if len(gid) != GID_SIZE:
        raise UsageError(f"a GID is {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence, stamp_ns, GID_SIZE) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time ns, GID) of an attachment; ValueError if it is not one."""
    if len(data) != 17 + GID_SIZE or data[16] != GID_SIZE:
        raise UsageError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    sequence, stamp_ns = struct.unpack_from("<qq", data)
    return sequence, stamp_ns, data[17:]


class Publisher:
    """One topic published by an `RmwNode` (serialised messages in, samples with attachments out)."""

    def __init__(self, node: RmwNode, topic: str, typename: str, qos: QoS, entity_id: int) -> None:
        self.topic, self.typename, self.qos = topic, typename, qos
        self.gid = os.urandom(GID_SIZE)
        self.key = topic_key(node.domain_id, topic, typename)
        self.token = endpoint_token(node.domain_id, node.zid, node.node_id, entity_id, "MP", node.namespace,
                                    node.name, topic, typename, qos)
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()
        self._wall = node.clock.wall
        reliability = zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT
        self._pub = node.session.declare_publisher(self.key, encoding=zenoh.Encoding("application/cdr"),
                                                   congestion_control=zenoh.CongestionControl.DROP,
                                                   reliability=reliability)
        self._token = node.session.liveliness().declare_token(self.token)

    def put(self, payload: bytes, stamp_ns: int | None = None) -> None:
        """Send one CDR payload (as `messages.serialize` makes it)."""
        with self._lock:
            sequence = next(self._sequence)
        self._pub.put(payload, attachment=attachment(sequence, stamp_ns or _ns(self._wall()), self.gid))

    def close(self) -> None:
        self._token.undeclare()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs
        self._pub.undeclare()  # type: ignore[no-untyped-call]


class Subscription:
    """One topic an `RmwNode` listens to: `callback(payload)` with each sample's CDR bytes, on Zenoh's thread."""

    def __init__(self, node: RmwNode, topic: str, typename: str, qos: QoS, entity_id: int,
                 callback: Callable[[bytes], None]) -> None:
        self.topic, self.typename, self.qos = topic, typename, qos
        self.key = topic_key(node.domain_id, topic, typename)
        self.token = endpoint_token(node.domain_id, node.zid, node.node_id, entity_id, "MS", node.namespace,
                                    node.name, topic, typename, qos)
        self._sub = node.session.declare_subscriber(self.key, lambda sample: callback(sample.payload.to_bytes()))
        self._token = node.session.liveliness().declare_token(self.token)

    def close(self) -> None:
        self._token.undeclare()  # type: ignore[no-untyped-call]
        self._sub.undeclare()  # type: ignore[no-untyped-call]


class Request:
    """A service request taken by a `Service`: its CDR payload, the client's sequence number and GID, and
    `reply(payload)`, which may be called later from any thread (once; later calls do nothing)."""

    def __init__(self, service: Service, query: zenoh.Query, payload: bytes, sequence: int, gid: bytes) -> None:
        self.service, self.payload, self.sequence, self.gid = service, payload, sequence, gid
        self._query: zenoh.Query | None = query
        self._lock = threading.Lock()

    def reply(self, payload: bytes) -> bool:
        """Send the response (CDR) with rmw_zenoh's attachment: the request's sequence number and the
        client's GID, the time of the reply. False if already answered or the session is gone."""
        with self._lock:
            query, self._query = self._query, None
        if query is None:
            return False
        try:
            query.reply(self.service.key, payload, encoding=zenoh.Encoding("application/cdr"),
                        attachment=attachment(self.sequence, _ns(self.service.clock.wall()), self.gid))
        except zenoh.ZError:
            return False
        finally:
            query.drop()  # type: ignore[no-untyped-call]  # the reply is final: the client's get ends here
        return True

    def fail(self, message: str) -> bool:
        """Answer with a Zenoh error reply instead (a request that cannot be served); False if already answered."""
        with self._lock:
            query, self._query = self._query, None
        if query is None:
            return False
        try:
            query.reply_err(message.encode())
        except zenoh.ZError:
            return False
        finally:
            query.drop()  # type: ignore[no-untyped-call]
        return True


class Service:
    """A service server of an `RmwNode`: a queryable on the service's key expression (as a topic's,
    with the service's type: 'std_srvs::srv::dds_::Trigger_' and its RIHS01 hash), its `SS` token;
    `handler(request)` runs on Zenoh's thread and answers with `request.reply(...)`, now or later."""

    def __init__(self, node: RmwNode, name: str, srvtype: str, qos: QoS, entity_id: int,
                 handler: Callable[[Request], None]) -> None:
        self.name, self.srvtype, self.qos = name, srvtype, qos
        self.key = topic_key(node.domain_id, name, srvtype)
        self.token = endpoint_token(node.domain_id, node.zid, node.node_id, entity_id, "SS", node.namespace,
                                    node.name, name, srvtype, qos)
        self._handler = handler
        self.clock = node.clock
        self._queryable = node.session.declare_queryable(self.key, self._on_query, complete=True)
        self._token = node.session.liveliness().declare_token(self.token)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            if query.attachment is None:
                raise UsageError("no attachment")
            sequence, _, gid = parse_attachment(query.attachment.to_bytes())
        except UsageError as err:
            query.reply_err(f"{self.name}: request refused: {err}".encode())
            return
        self._handler(Request(self, query, payload, sequence, gid))

    def close(self) -> None:
        self._token.undeclare()  # type: ignore[no-untyped-call]
        self._queryable.undeclare()  # type: ignore[no-untyped-call]


class RmwNode:
    """A ROS 2 node as rmw_zenoh shows it (its token, its publishers' and subscriptions' tokens) on a
    Zenoh session that may be shared with others (each `RmwNode` takes its own node id)."""

    _node_ids = itertools.count(1000)  # ids unique in this process (a shared session may hold several nodes)

    def __init__(self, session: zenoh.Session, name: str, *, namespace: str = "/", domain_id: int = 0,
                 clock: Clock = SYSTEM) -> None:
        self.session, self.name, self.namespace, self.domain_id = session, name, namespace, domain_id
        self.clock = clock  # its wall readings stamp what it sends without a stamp of its own
        self.zid = str(session.info.zid())
        self.node_id = next(self._node_ids)
        self._entity_ids = itertools.count(self.node_id * 1000 + 1)
        self.token = node_token(domain_id, self.zid, self.node_id, namespace, name)
        self._token = session.liveliness().declare_token(self.token)
        self.publishers: dict[str, Publisher] = {}
        self.subscriptions: dict[str, Subscription] = {}
        self.services: dict[str, Service] = {}
        self._lock = threading.Lock()

    def publisher(self, topic: str, typename: str, qos: QoS = DEFAULT_QOS) -> Publisher:
        """The node's publisher of `topic` (declared on first use)."""
        with self._lock:
            pub = self.publishers.get(topic)
            if pub is None:
                pub = self.publishers[topic] = Publisher(self, topic, typename, qos, next(self._entity_ids))
            return pub

    def subscribe(self, topic: str, typename: str, callback: Callable[[bytes], None],
                  qos: QoS = DEFAULT_QOS) -> Subscription:
        """Listen to `topic` (once per topic)."""
        with self._lock:
            sub = self.subscriptions.get(topic)
            if sub is None:
                sub = self.subscriptions[topic] = Subscription(self, topic, typename, qos, next(self._entity_ids),
                                                               callback)
            return sub

    def service(self, name: str, srvtype: str, handler: Callable[[Request], None],
                qos: QoS = DEFAULT_QOS) -> Service:
        """Serve `name` (once per name): rclcpp's services default QoS is the topics' (reliable, keep last 10)."""
        with self._lock:
            srv = self.services.get(name)
            if srv is None:
                srv = self.services[name] = Service(self, name, srvtype, qos, next(self._entity_ids), handler)
            return srv

    def close(self) -> None:
        """Undeclare every publisher, subscription and the node's token (the session stays open)."""
        with self._lock:
            entities: list[Any] = [*self.publishers.values(), *self.subscriptions.values(),
                                   *self.services.values()]
            self.publishers.clear()
            self.subscriptions.clear()
            self.services.clear()
        for entity in entities:
            try:
                entity.close()
            except zenoh.ZError:
                pass  # the session closed first: its declarations went with it
        try:
            self._token.undeclare()  # type: ignore[no-untyped-call]
        except zenoh.ZError:
            pass
