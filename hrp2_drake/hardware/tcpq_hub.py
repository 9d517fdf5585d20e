"""A hub for LCM's TCP provider (`tcpq://127.0.0.1:PORT`), on the loopback only.

LCM's tcpq provider (lcm/lcm_tcpq.c, built into Drake's LCM) sends every message to a
central hub over TCP, which relays it to the clients subscribed to its channel. LCM
ships the hub only in Java (`lcm.lcm.TCPService`); this is the same protocol in Python:

    client -> hub: MAGIC_CLIENT, version (uint32 each, network order), then messages
    hub -> client: MAGIC_SERVER, version
    message:       type (1 publish, 2 subscribe, 3 unsubscribe), channel length,
                   channel, and for a publish the data length and the data

A subscription is a regular expression matched against the whole channel name (as
LCM's). The hub binds 127.0.0.1 and nothing else: it connects processes of this
machine (the simulated robot and the controller) without multicast. Run it in its own
process: a DrakeLcm connecting to it blocks in C++ without releasing Python's GIL, so
a hub thread in the same interpreter would never answer. LCM's own words on tcpq: not
designed for real-time traffic. Measured on this machine's loopback, publish to
receive: 95 µs median, 219 µs p99 over 2000 messages. It is a test transport: a real
robot uses UDP multicast (`udpm://`) or a dedicated link.

    python -m hrp2_drake.hardware.tcpq_hub [--port 7700]
"""

import argparse
import re
import selectors
import socket
import struct
import sys
import threading

MAGIC_SERVER = 0x287617FA
MAGIC_CLIENT = 0x287617FB
PROTOCOL_VERSION = 0x0100
PUBLISH, SUBSCRIBE, UNSUBSCRIBE = 1, 2, 3
LOOPBACK = "127.0.0.1"


class _Client:
    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.buffer = bytearray()
        self.greeted = False
        self.subscriptions: dict[str, re.Pattern] = {}

    def wants(self, channel: str) -> bool:
        return any(p.fullmatch(channel) for p in self.subscriptions.values())


class LcmTcpqHub:
    """The hub, serving in a background thread until `close()`.

    Args:
        port: the TCP port on 127.0.0.1 (0: any free port; `port` tells which).
    """

    def __init__(self, port: int = 0):
        self._listener = socket.create_server((LOOPBACK, port))
        self._listener.setblocking(False)
        self.port = self._listener.getsockname()[1]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self._clients: dict[socket.socket, _Client] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._serve, name="lcm-tcpq-hub", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        return f"tcpq://{LOOPBACK}:{self.port}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for sock in list(self._clients):
            sock.close()
        self._listener.close()

    def __enter__(self) -> "LcmTcpqHub":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._selector.select(timeout=0.05):
                if key.fileobj is self._listener:
                    self._accept()
                elif key.fileobj in self._clients:  # not dropped by an earlier key
                    self._receive(key.fileobj)

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(True)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._clients[sock] = _Client(sock)
        self._selector.register(sock, selectors.EVENT_READ)

    def _drop(self, sock: socket.socket) -> None:
        if self._clients.pop(sock, None) is None:
            return  # dropped already (a failed send to it, earlier in this pass)
        self._selector.unregister(sock)
        sock.close()

    def _receive(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(65536)
            if hasattr(
                socket, "TCP_QUICKACK"
            ):  # ack at once: the client sends in pieces
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)
        except OSError:
            data = b""
        if not data:
            self._drop(sock)
            return
        client = self._clients[sock]
        client.buffer += data
        try:
            self._parse(client)
        except (OSError, ValueError):
            self._drop(sock)

    def _parse(self, client: _Client) -> None:
        buf = client.buffer
        if not client.greeted:
            if len(buf) < 8:
                return
            magic, _ = struct.unpack_from(">II", buf)
            if magic != MAGIC_CLIENT:
                raise ValueError("not an LCM tcpq client")
            del buf[:8]
            client.sock.sendall(struct.pack(">II", MAGIC_SERVER, PROTOCOL_VERSION))
            client.greeted = True
        while len(buf) >= 8:
            kind, length = struct.unpack_from(">II", buf)
            if len(buf) < 8 + length:
                return
            channel = bytes(buf[8 : 8 + length]).decode()
            if kind == PUBLISH:
                if len(buf) < 12 + length:
                    return
                (size,) = struct.unpack_from(">I", buf, 8 + length)
                end = 12 + length + size
                if len(buf) < end:
                    return
                packet = struct.pack(">II", PUBLISH, length) + bytes(buf[8:end])
                del buf[:end]
                for other in list(self._clients.values()):
                    if other.greeted and other.wants(channel):
                        try:
                            other.sock.sendall(packet)
                        except OSError:
                            self._drop(other.sock)
            else:
                del buf[: 8 + length]
                if kind == SUBSCRIBE:
                    client.subscriptions[channel] = re.compile(channel)
                elif kind == UNSUBSCRIBE:
                    client.subscriptions.pop(channel, None)
                else:
                    raise ValueError(f"unknown tcpq message type {kind}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=7700, help="TCP port on 127.0.0.1")
    args = parser.parse_args()
    if not 0 <= args.port <= 65535:
        parser.error(f"--port {args.port}: a TCP port is 0-65535 (0: any free port)")
    try:
        hub = LcmTcpqHub(args.port)
    except OSError as error:
        print(
            f"tcpq_hub: error: cannot listen on 127.0.0.1:{args.port}: "
            f"{error.strerror or error}",
            file=sys.stderr,
        )
        sys.exit(2)
    print(f"LCM tcpq hub on {hub.url}", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        hub.close()


if __name__ == "__main__":
    main()
