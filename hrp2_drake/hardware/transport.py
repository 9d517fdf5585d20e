"""LCM transports for the message-driven loops: subscribe, publish, handle, and a clean
end when the transport itself goes away.

Two implementations behind one interface (`Transport`):

- `TcpqTransport` speaks LCM's TCP provider protocol (`tcpq://127.0.0.1:PORT`, the one
  `tcpq_hub` serves) from Python sockets. LCM's own C provider aborts the whole process
  when its hub disappears (glibc's `*** bit out of range 0 - FD_SETSIZE on fd_set ***`:
  after the disconnect it passes fd −1 to FD_SET), and it blocks without a timeout in
  `connecting...` when the listener is not a hub. Here a lost hub is a
  `TransportClosed` the loop handles (ramp, report, one line), and connecting times out
  with a message that says what answered.
- `DrakeLcmTransport` wraps Drake's `DrakeLcm` for `memq://` (in-process tests) and
  `udpm://` (a robot's network).

Messages are the encoded bytes of LCM types (`messages.py`); a handler gets them as
`bytes`.
"""

import ipaddress
import re
import selectors
import socket
import struct
import time
from collections.abc import Callable
from typing import Protocol
from urllib.parse import urlparse

from hrp2_drake.hardware.link import LinkClosed
from hrp2_drake.hardware.tcpq_hub import (
    MAGIC_CLIENT,
    MAGIC_SERVER,
    PROTOCOL_VERSION,
    PUBLISH,
    SUBSCRIBE,
)

Handler = Callable[[bytes], None]
SCHEMES = ("tcpq", "udpm", "memq")


class TransportClosed(LinkClosed):
    """The transport is gone (the hub closed the connection, the socket failed)."""


class Transport(Protocol):
    url: str

    def subscribe(self, channel: str, handler: Handler) -> None: ...

    def publish(self, channel: str, data: bytes) -> None: ...

    def publish_many(self, messages: list[tuple[str, bytes]]) -> None:
        """Publishes the messages in order (one send where the transport can)."""
        ...

    def handle(self, timeout: float) -> int:
        """Dispatches the messages that arrive within `timeout` s (returns once at least
        one was handled, or at the timeout): how many. TransportClosed if it is gone."""
        ...

    def close(self) -> None: ...


def check_url(url: str) -> str:
    """The URL if it names a transport this project can open; a ValueError in one line
    that says what is wrong otherwise (scheme, host, port, multicast group)."""
    parsed = urlparse(url)
    if parsed.scheme not in SCHEMES:
        raise ValueError(
            f"LCM URL '{url}': unknown scheme '{parsed.scheme}' (use one of "
            f"{', '.join(s + '://' for s in SCHEMES)})"
        )
    if parsed.scheme == "memq":
        return url
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError as error:
        raise ValueError(f"LCM URL '{url}': {error}") from None
    try:
        address = ipaddress.ip_address(host or "")
    except ValueError:
        raise ValueError(f"LCM URL '{url}': '{host}' is not an IP address") from None
    if parsed.scheme == "udpm" and not address.is_multicast:
        raise ValueError(f"LCM URL '{url}': {address} is not a multicast group")
    if parsed.scheme == "tcpq" and not address.is_loopback:
        raise ValueError(
            f"LCM URL '{url}': tcpq connects processes of this machine: use 127.0.0.1"
        )
    if port is None or not 0 < port < 65536:
        raise ValueError(f"LCM URL '{url}': a port in 1-65535 is needed")
    return url


def open_transport(url: str, timeout: float = 2.0) -> Transport:
    """The transport of `url` (`check_url`); connecting to a tcpq hub waits at most
    `timeout` s."""
    check_url(url)
    if url.startswith("tcpq://"):
        parsed = urlparse(url)
        return TcpqTransport(parsed.hostname, parsed.port, timeout)
    return DrakeLcmTransport(url)


class TcpqTransport:
    """A client of an LCM tcpq hub (module docstring).

    Raises (at construction) ConnectionError naming the URL when nothing listens, when
    the listener does not answer as a hub within `timeout` s, or answers something
    else.
    """

    def __init__(self, host: str, port: int, timeout: float = 2.0):
        self.url = f"tcpq://{host}:{port}"
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as error:
            raise ConnectionError(
                f"{self.url}: cannot connect ({error.strerror or error}): is the hub "
                "running (python -m hrp2_drake.hardware.tcpq_hub --port PORT)?"
            ) from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            self._sock.sendall(struct.pack(">II", MAGIC_CLIENT, PROTOCOL_VERSION))
            greeting = self._read_exactly(8, time.monotonic() + timeout)
        except (OSError, TransportClosed) as error:
            self._sock.close()
            raise ConnectionError(
                f"{self.url}: the listener did not answer as an LCM tcpq hub within "
                f"{timeout:g} s ({error})"
            ) from None
        magic, _ = struct.unpack(">II", greeting)
        if magic != MAGIC_SERVER:
            self._sock.close()
            raise ConnectionError(f"{self.url}: the listener is not an LCM tcpq hub")
        self._sock.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._sock, selectors.EVENT_READ)
        self._buffer = bytearray()
        self._handlers: list[tuple[re.Pattern, Handler]] = []
        self._closed = False

    def _read_exactly(self, size: int, deadline: float) -> bytes:
        data = b""
        while len(data) < size:
            self._sock.settimeout(max(deadline - time.monotonic(), 1e-3))
            chunk = self._sock.recv(size - len(data))
            if not chunk:
                raise TransportClosed("the connection closed")
            data += chunk
        return data

    def subscribe(self, channel: str, handler: Handler) -> None:
        self._handlers.append((re.compile(channel), handler))
        name = channel.encode()
        self._send(struct.pack(">II", SUBSCRIBE, len(name)) + name)

    def publish(self, channel: str, data: bytes) -> None:
        self._send(self._packet(channel, data))

    def publish_many(self, messages: list[tuple[str, bytes]]) -> None:
        """One send for all: on this loopback each send costs tens of µs."""
        self._send(b"".join(self._packet(channel, data) for channel, data in messages))

    @staticmethod
    def _packet(channel: str, data: bytes) -> bytes:
        name = channel.encode()
        return (
            struct.pack(">II", PUBLISH, len(name))
            + name
            + struct.pack(">I", len(data))
            + data
        )

    def _send(self, packet: bytes) -> None:
        if self._closed:
            raise TransportClosed(f"{self.url}: closed")
        view = memoryview(packet)
        while view:
            try:
                sent = self._sock.send(view)
            except BlockingIOError:
                selectors.select.select([], [self._sock], [], 0.1)
                continue
            except OSError as error:
                self._closed = True
                raise TransportClosed(
                    f"{self.url}: the hub went away ({error})"
                ) from None
            view = view[sent:]

    def handle(self, timeout: float) -> int:
        if self._closed:
            raise TransportClosed(f"{self.url}: closed")
        if not self._selector.select(timeout):
            return 0
        try:
            data = self._sock.recv(1 << 16)
        except BlockingIOError:
            return 0
        except OSError as error:
            self._closed = True
            raise TransportClosed(f"{self.url}: the hub went away ({error})") from None
        if not data:
            self._closed = True
            raise TransportClosed(f"{self.url}: the hub closed the connection")
        self._buffer += data
        return self._dispatch()

    def _dispatch(self) -> int:
        buf, handled, start = self._buffer, 0, 0
        while len(buf) - start >= 8:
            kind, length = struct.unpack_from(">II", buf, start)
            if kind != PUBLISH or length > 1024:
                self._closed = True
                raise TransportClosed(f"{self.url}: the hub sent a malformed packet")
            header = start + 8 + length
            if len(buf) < header + 4:
                break
            (size,) = struct.unpack_from(">I", buf, header)
            end = header + 4 + size
            if len(buf) < end:
                break
            channel = bytes(buf[start + 8 : header]).decode(errors="replace")
            data = bytes(buf[header + 4 : end])
            start = end
            for pattern, handler in self._handlers:
                if pattern.fullmatch(channel):
                    handler(data)
                    handled += 1
        del buf[:start]
        return handled

    def close(self) -> None:
        if not self._closed:
            self._closed = True
        self._selector.close()
        self._sock.close()


class DrakeLcmTransport:
    """Drake's DrakeLcm (`memq://`, `udpm://`) as a Transport."""

    def __init__(self, url: str):
        from pydrake.lcm import DrakeLcm

        self.url = url
        try:
            self._lcm = DrakeLcm(url)
        except RuntimeError as error:
            raise ConnectionError(f"{url}: {' '.join(str(error).split())}") from None

    @property
    def lcm(self):
        """The DrakeLcm (for code that takes one, e.g. Drake's LCM systems)."""
        return self._lcm

    def subscribe(self, channel: str, handler: Handler) -> None:
        self._lcm.Subscribe(channel, handler)

    def publish(self, channel: str, data: bytes) -> None:
        self._lcm.Publish(channel, data)

    def publish_many(self, messages: list[tuple[str, bytes]]) -> None:
        for channel, data in messages:
            self._lcm.Publish(channel, data)

    def handle(self, timeout: float) -> int:
        return self._lcm.HandleSubscriptions(int(timeout * 1000))

    def close(self) -> None:
        pass
