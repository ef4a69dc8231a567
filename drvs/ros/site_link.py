"""The site link: topics of another site's ROS master copied onto this one, for the simulation.

One simulated world runs at one site; the nodes of another site, on a master of their own, need
some of its topics (``/clock``, ``/world_sim/poses``). The link asks the other master for each
topic's publishers (XML-RPC ``getSystemState``, ``lookupNode``), asks each publisher for a TCPROS
connection (``requestTopic``), subscribes over it without registering with that master, and
publishes every message here, as the bytes it received, under the same name and type. Real sites
have their own clocks and their own camera poses: the link exists for the simulation only.
docs/nodes/drvs_site_link.md has the rest.
"""

from __future__ import annotations

import socket
import struct
import threading
import xmlrpc.client

import rospy

from drvs.ros.node import NodeScaffold
from drvs.ros.tcpros import Deadline, ServiceCallError, TimeoutTransport, handshake
from drvs.sim.params import SiteLinkSettings

__all__ = ['SiteLinkNode', 'raw_message_class']

MAX_MESSAGE_BYTES = 64 << 20
"""A larger length prefix is a broken stream, not a message: the connection is dropped."""

READ_PERIOD = 0.5
"""Seconds a connection's read waits before it looks whether the node is stopping."""


class LinkBroken(Exception):
    """A connection to a publisher failed or ended; the message says which and why."""


def raw_message_class(type_name: str, md5sum: str, definition: str) -> type:
    """A message class of type ``type_name`` whose instances hold their serialized bytes (``_buff``),
    published as they are: no decoding, any type, the md5sum and definition of the original."""
    return type(
        'Raw_' + type_name.replace('/', '_'),
        (rospy.AnyMsg,),
        {'__slots__': (), '_type': type_name, '_md5sum': md5sum, '_full_text': definition},
    )


class SiteLinkNode:
    """Polls the other master for the publishers of ``~topics``; one connection thread per publisher."""

    COUNTERS = ('messages', 'connections', 'broken')

    def __init__(self, settings: SiteLinkSettings):
        self.settings = settings
        self.topics = settings.topic_names
        self.node = NodeScaffold(None, self.COUNTERS)  # no /diagnostics: the link is no part of DRVS
        self._lock = threading.Lock()  # guards _publishers and _connected
        self._publishers: dict[str, tuple[rospy.Publisher, str]] = {}  # topic -> (here, its md5sum)
        self._connected: set[tuple[str, str]] = set()  # (topic, publisher node) with a live connection
        self._caller_id = ''

    def start(self) -> None:
        self._caller_id = rospy.get_name()
        rospy.loginfo('%s: copying %s from %s', self._caller_id, ', '.join(self.topics), self.settings.master)
        self.node.every(self.settings.poll_period, self.poll, 'poll')
        self.poll()

    def stop(self) -> None:
        self.node.stop(join=2 * READ_PERIOD)

    # -- the other master ------------------------------------------------------------------------
    def _master(self) -> xmlrpc.client.ServerProxy:
        return xmlrpc.client.ServerProxy(
            self.settings.master, transport=TimeoutTransport(self.settings.timeout)
        )

    def poll(self) -> None:
        """Connect to every publisher of ``~topics`` the other master lists and we are not connected to."""
        try:
            with self._master() as master:
                code, message, state = master.getSystemState(self._caller_id)
                if code != 1:
                    raise LinkBroken(f'getSystemState: {message}')
                listed = {topic: nodes for topic, nodes in state[0] if topic in self.topics}
                wanted = []
                for topic, nodes in listed.items():
                    for name in nodes:
                        with self._lock:
                            if (topic, name) in self._connected:
                                continue
                        code, message, uri = master.lookupNode(self._caller_id, name)
                        if code == 1:
                            wanted.append((topic, name, uri))
        except (OSError, xmlrpc.client.Error, LinkBroken) as error:
            self.node.log_throttled(
                'master',
                rospy.logwarn,
                '%s: cannot ask the master %s: %s',
                self._caller_id,
                self.settings.master,
                error,
            )
            return
        for topic, name, uri in wanted:
            with self._lock:
                if (topic, name) in self._connected:
                    continue
                self._connected.add((topic, name))
            self.node.spawn(
                lambda t=topic, n=name, u=uri: self._follow(t, n, u), f'link {topic} {name}', 'shutdown'
            )

    # -- one publisher ---------------------------------------------------------------------------
    def _follow(self, topic: str, name: str, uri: str) -> None:
        """Copy ``topic`` from the publisher ``name`` at ``uri`` until the connection ends."""
        sock = None
        try:
            sock = self._subscribe(topic, name, uri)
            self.node.counters.add(connections=1)
            rospy.loginfo('%s: %s from %s (%s)', self._caller_id, topic, name, uri)
            while not self.node.stopped:
                (size,) = struct.unpack('<I', self._read(sock, 4, topic, name))
                if size > MAX_MESSAGE_BYTES:
                    raise LinkBroken(
                        f'{topic} from {name}: a message of {size} bytes; dropping the connection'
                    )
                self._publish(topic, self._read(sock, size, topic, name))
        except LinkBroken as error:
            if self.node.stopped:
                return
            self.node.counters.add(broken=1)
            if sock is None:  # not connected: a publisher the master still lists after it died, say
                self.node.log_throttled(
                    (topic, name), rospy.logwarn, '%s: %s; trying again', self._caller_id, error
                )
            else:
                rospy.loginfo(
                    '%s: %s; connecting again when %s lists it', self._caller_id, error, self.settings.master
                )
        finally:
            if sock is not None:
                sock.close()
            with self._lock:
                self._connected.discard((topic, name))

    def _subscribe(self, topic: str, name: str, uri: str) -> socket.socket:
        """A TCPROS connection to ``topic`` of the publisher ``name``, past the handshake; the topic's
        publisher here made from the publisher's header the first time."""
        timeout = self.settings.timeout
        try:
            with xmlrpc.client.ServerProxy(uri, transport=TimeoutTransport(timeout)) as publisher:
                code, message, protocol = publisher.requestTopic(self._caller_id, topic, [['TCPROS']])
        except (OSError, xmlrpc.client.Error) as error:
            raise LinkBroken(f'{topic} from {name}: requestTopic at {uri} failed: {error}') from None
        if code != 1 or len(protocol) != 3 or protocol[0] != 'TCPROS':
            raise LinkBroken(f'{topic} from {name}: no TCPROS connection offered ({message})')
        _, host, port = protocol
        try:
            sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as error:
            raise LinkBroken(f'{topic} from {name}: cannot connect to {host}:{port}: {error}') from None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)  # the handshake waits with the service client's own steps
            fields = {
                'callerid': self._caller_id,
                'topic': topic,
                'md5sum': '*',
                'type': '*',
                'tcp_nodelay': '1',
            }
            try:
                header = handshake(sock, fields, Deadline(f'{topic} from {name}', timeout))
            except ServiceCallError as error:
                raise LinkBroken(str(error).removeprefix('service ')) from None
            sock.settimeout(READ_PERIOD)  # then the messages: read in steps that look at the stop
            self._advertise(topic, header)
        except (LinkBroken, OSError) as error:
            sock.close()
            raise LinkBroken(str(error)) from None
        return sock

    def _advertise(self, topic: str, header: dict[str, str]) -> None:
        """This side's publisher of ``topic``, as the first publisher's header describes it.

        :raises LinkBroken: a later publisher of another type (another md5sum).
        """
        md5sum = header.get('md5sum', '')
        with self._lock:
            made = self._publishers.get(topic)
            if made is None:
                data_class = raw_message_class(
                    header.get('type', ''), md5sum, header.get('message_definition', '')
                )
                publisher = rospy.Publisher(
                    topic,
                    data_class,
                    queue_size=self.settings.queue_size,
                    latch=header.get('latching') == '1',
                )
                self._publishers[topic] = (publisher, md5sum)
            elif made[1] != md5sum:
                raise LinkBroken(
                    f'{topic} from {header.get("callerid", "?")}: type {header.get("type")} differs from the '
                    'first publisher\'s (its md5sum too): not copied'
                )

    def _read(self, sock: socket.socket, count: int, topic: str, name: str) -> bytes:
        """Exactly ``count`` bytes, as long as it takes while the node is not stopping."""
        data = bytearray()
        while len(data) < count:
            try:
                chunk = sock.recv(min(count - len(data), 1 << 20))
            except TimeoutError:
                if self.node.stopped:
                    raise LinkBroken(f'{topic} from {name}: stopping') from None
                continue
            except OSError as error:
                raise LinkBroken(f'{topic} from {name}: connection failed: {error}') from None
            if not chunk:
                raise LinkBroken(f'{topic} from {name}: connection closed by the publisher')
            data += chunk
        return bytes(data)

    def _publish(self, topic: str, data: bytes) -> None:
        with self._lock:
            publisher, _ = self._publishers[topic]
        message = publisher.data_class()
        message._buff = data
        publisher.publish(message)
        self.node.counters.add(messages=1)
