"""bench/capture.py: a known exchange between two local sockets is counted to the byte.

Needs root (an AF_PACKET socket on ``lo``); skipped with the reason otherwise.
The framer and header parser are also checked without a capture.
"""

import socket
import struct

import pytest

from bench import capture
from bench.capture import Capture, CaptureError, Framer, parse_header

CAN_CAPTURE, WHY_NOT = capture.available()
needs_capture = pytest.mark.skipif(not CAN_CAPTURE, reason=WHY_NOT or 'capture available')


def header(**fields: str) -> bytes:
    """A TCPROS connection header: length, then length-prefixed ``key=value`` fields."""
    body = b''.join(struct.pack('<I', len(f'{k}={v}')) + f'{k}={v}'.encode() for k, v in fields.items())
    return struct.pack('<I', len(body)) + body


def message(data: bytes) -> bytes:
    return struct.pack('<I', len(data)) + data


def response(data: bytes, ok: bool = True) -> bytes:
    return struct.pack('<BI', ok, len(data)) + data


CLIENT_HEADER = header(callerid='/robot', service='/vs1/detect', md5sum='*', persistent='1')
SERVER_HEADER = header(callerid='/vs1', md5sum='abc', type='drvs/Detect')
REQUESTS = [message(b'x' * 100), message(b''), message(b'y' * 70_000)]  # the last spans packets
RESPONSES = [response(b'ok'), response(b'failed', ok=False), response(b'z' * 5)]


def test_parse_header_reads_fields_with_equals_signs_in_values():
    assert parse_header(CLIENT_HEADER[4:]) == {
        'callerid': '/robot',
        'service': '/vs1/detect',
        'md5sum': '*',
        'persistent': '1',
    }


def test_parse_header_refuses_a_truncated_field():
    with pytest.raises(ValueError, match='truncated field'):
        parse_header(struct.pack('<I', 10) + b'a=b')


def test_framer_counts_a_service_stream_fed_one_byte_at_a_time():
    up, down = Framer(), Framer(response=True)
    for byte in CLIENT_HEADER + b''.join(REQUESTS):
        up.feed(bytes([byte]))
    for byte in SERVER_HEADER + b''.join(RESPONSES):
        down.feed(bytes([byte]))
    assert (up.header_bytes, up.messages, up.message_bytes) == (
        len(CLIENT_HEADER),
        3,
        sum(map(len, REQUESTS)),
    )
    assert (down.header_bytes, down.messages, down.message_bytes, down.errors) == (
        len(SERVER_HEADER),
        3,
        sum(map(len, RESPONSES)),
        1,
    )
    assert up.fields['service'] == '/vs1/detect'


def test_framer_leaves_http_unframed():
    framer = Framer()
    framer.feed(b'POST /RPC2 HTTP/1.1\r\n')
    assert framer.state == 'http'
    assert framer.messages == 0


def recv_exactly(sock: socket.socket, size: int) -> bytes:
    data = b''
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        assert chunk, 'closed early'
        data += chunk
    return data


@needs_capture
def test_capture_counts_a_known_tcpros_exchange_exactly():
    ports: set[int] = set()
    with Capture(ports) as cap:
        server = socket.socket()
        server.bind(('127.0.0.1', 0))
        server.listen(1)
        ports.add(server.getsockname()[1])
        with server, socket.create_connection(server.getsockname()) as client:
            accepted, _ = server.accept()
            with accepted:
                client.sendall(CLIENT_HEADER)
                recv_exactly(accepted, len(CLIENT_HEADER))
                accepted.sendall(SERVER_HEADER)
                recv_exactly(client, len(SERVER_HEADER))
                cap.flush()
                before = cap.snapshot()
                for request, reply in zip(REQUESTS, RESPONSES, strict=True):
                    client.sendall(request)
                    recv_exactly(accepted, len(request))
                    accepted.sendall(reply)
                    recv_exactly(client, len(reply))
                cap.flush()
                after = cap.snapshot()
                client_port = client.getsockname()[1]
    (connection,) = [c for c in after.values() if c.client[1] == client_port]
    assert connection.syn_seen and connection.kind == 'service' and connection.caller == '/robot'
    assert connection.server == ('127.0.0.1', min(ports))
    assert connection.up.bytes == len(CLIENT_HEADER) + sum(map(len, REQUESTS))
    assert connection.down.bytes == len(SERVER_HEADER) + sum(map(len, RESPONSES))
    assert connection.header_bytes == len(CLIENT_HEADER) + len(SERVER_HEADER)
    assert (connection.up.framer.messages, connection.down.framer.messages) == (3, 3)
    assert connection.down.framer.errors == 1
    assert connection.up.gaps == connection.down.gaps == 0
    ((changed, up, down),) = capture.delta(before, after)
    assert changed.id == connection.id
    assert (up, down) == (sum(map(len, REQUESTS)), sum(map(len, RESPONSES)))
    assert cap.drops == 0


@needs_capture
def test_capture_ignores_ports_not_of_interest():
    with Capture(set()) as cap, socket.socket() as server:
        server.bind(('127.0.0.1', 0))
        server.listen(1)
        with socket.create_connection(server.getsockname()) as client:
            client.sendall(b'hello')
            cap.flush()
        assert cap.snapshot() == {}
        assert cap.ignored > 0


@needs_capture
def test_a_dead_capture_thread_fails_loudly(monkeypatch):
    def broken(self, frame):
        raise RuntimeError('parser bug')

    monkeypatch.setattr(Capture, '_packet', broken)
    with Capture(None) as cap:  # flush's own marker packet reaches the broken parser
        with pytest.raises(CaptureError, match='capture thread died: RuntimeError: parser bug'):
            cap.flush()
        with pytest.raises(CaptureError, match='parser bug'):
            cap.snapshot()
