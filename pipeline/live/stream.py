"""Where a live run's frames are shown as they happen: a Rerun viewer, a Foxglove server.

The Rerun recording goes to a viewer's gRPC address (one spawned for the run, or
one already running) beside its .rrd file; the MCAP's messages go, as written, to
a Foxglove WebSocket server on the same topics (``foxglove-sdk``).
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any
from urllib.parse import urlsplit

from ..errors import SettingsError
from ..record.mcap_log import TF_TOPIC, ChannelSchema

log = logging.getLogger(__name__)

DEFAULT_VIEWER_PORT = 9876  # Rerun's
DEFAULT_FOXGLOVE = "127.0.0.1:8765"  # Foxglove's usual WebSocket address
CONNECT_TIMEOUT_S = 2.0
# The longest the run waits for the Foxglove server's clients to close when it stops.
STOP_TIMEOUT_S = 5.0
# How long the server goes on serving, once the run stops, for its subscribers to take
# the messages queued for them: the SDK's stop drops whatever is still queued, and has
# no way to wait for a client's queue to empty. A client that keeps up holds a frame or two.
DRAIN_S = 0.5


def grpc_url(address: str) -> str:
    """A viewer's address as Rerun's gRPC URL: a port, HOST:PORT, or a ``rerun+http://`` URL."""
    text = address.strip()
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    if "://" not in text:
        text = f"rerun+http://{text}/proxy"
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:  # not a number, or past 65535
        port = None
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname or not port:
        raise SettingsError(
            f"--viewer connect {address!r}: not a Rerun viewer address; give PORT, HOST:PORT or "
            "rerun+http://HOST:PORT/proxy"
        )
    return text


def check_viewer(url: str) -> None:
    """Refuse, before the run, a viewer address where no gRPC server answers: nothing
    listens (the stream would pile up), or what listens is no viewer (a web server, a
    service that never answers). A plain ``rerun+http`` address is asked for an HTTP/2
    greeting, which a Rerun viewer answers at once; a ``rerun+https`` one only connected to."""
    parts = urlsplit(url)
    assert parts.hostname is not None and parts.port is not None  # grpc_url's
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=CONNECT_TIMEOUT_S) as conn:
            wrong = "" if parts.scheme == "rerun+https" else _not_http2(conn)
    except OSError as exc:
        raise SettingsError(
            f"--viewer connect {url}: no Rerun viewer answers there ({exc.strerror or exc}); start one "
            "(rerun, or rerun --serve-grpc) or use --viewer spawn or none"
        ) from None
    if wrong:
        raise SettingsError(
            f"--viewer connect {url}: {wrong}, so it is no Rerun viewer; give the viewer's gRPC port "
            f"(rerun's is {DEFAULT_VIEWER_PORT}), or use --viewer spawn or none"
        )


# The greeting an HTTP/2 client opens with (RFC 9113, 3.4): the preface and an empty SETTINGS
# frame. A server answers with a SETTINGS frame of its own: 9 header bytes, type 4 fourth.
_H2_GREETING = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes((0, 0, 0, 4, 0, 0, 0, 0, 0))
_H2_SETTINGS = 4


def _not_http2(conn: socket.socket) -> str:
    """What the server on ``conn`` does instead of answering HTTP/2's greeting ("" if it answers)."""
    conn.sendall(_H2_GREETING)
    answer = b""
    try:
        while len(answer) < 4:
            more = conn.recv(64)
            if not more:
                break
            answer += more
    except TimeoutError:
        return f"the server there took the connection but did not answer within {CONNECT_TIMEOUT_S:g} s"
    if len(answer) >= 4 and answer[3] == _H2_SETTINGS:
        return ""
    if answer.startswith((b"HTTP/", b"<")):  # a status line, or an HTTP/0.9 error page
        status = answer.splitlines()[0][:60].decode(errors="replace")
        return f"the server there answers as a web server ({status})"
    closed = "" if answer else " (it closed the connection)"
    return f"the server there does not answer as a gRPC server{closed}"


def has_display() -> bool:
    """A window can be opened: not a headless Linux box (macOS and Windows always can)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def spawn_viewer(port: int = DEFAULT_VIEWER_PORT) -> str:
    """Start a Rerun viewer (or reuse the one on ``port``) and return its gRPC URL."""
    import rerun as rr

    # connect=False: the run's own stream connects to it, beside its file.
    rr.spawn(port=port, connect=False)
    return f"rerun+http://127.0.0.1:{port}/proxy"


def viewer_from_choice(choice: Sequence[str]) -> str | None:
    """``--viewer``'s words -> the viewer's gRPC URL, or None: ``spawn`` (the default; none
    where no window can open), ``none``, or ``connect ADDRESS``."""
    words = list(choice) or ["spawn"]
    if words == ["none"]:
        return None
    if words == ["spawn"]:
        if not has_display():
            log.warning(
                "no display to open a Rerun viewer on; streaming to none (--viewer connect ADDRESS "
                "streams to a running one; the .rrd is written either way)"
            )
            return None
        return spawn_viewer()
    if len(words) == 2 and words[0] == "connect":
        url = grpc_url(words[1])
        check_viewer(url)
        return url
    raise SettingsError(
        f"--viewer {' '.join(words)}: expected spawn, none, or connect ADDRESS (PORT, HOST:PORT or "
        "rerun+http://HOST:PORT/proxy)"
    )


def parse_host_port(text: str) -> tuple[str, int]:
    """``--foxglove``'s HOST:PORT (or PORT; an IPv6 host in brackets, ``[::1]:8765``) ->
    (host, port); port 0: any free one."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or int(port) > 65535:
        raise SettingsError(f"--foxglove {text!r}: expected HOST:PORT (e.g. {DEFAULT_FOXGLOVE}) or PORT")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host or "127.0.0.1", int(port)


def check_foxglove(host: str, port: int) -> None:
    """Refuse, before the run, a ``--foxglove`` address the server could not serve on: its
    port taken (another server, another live run), or a host that is not this machine's.
    Port 0 (any free one) always can."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        family, kind, proto, _, address = infos[0]
        with socket.socket(family, kind, proto) as probe:
            # As a server binds: a port that only connections closing hold is free for it.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as exc:
        why = exc.strerror or " ".join(str(exc).split())
        if exc.errno == errno.EADDRINUSE:
            raise SettingsError(
                f"--foxglove {host}:{port}: port {port} is taken ({why}); stop what serves there, or "
                "give another --foxglove HOST:PORT"
            ) from None
        raise SettingsError(
            f"--foxglove {host}:{port}: cannot serve there ({why}); give a HOST:PORT of this machine"
        ) from None


class FoxgloveServer:
    """A Foxglove WebSocket server publishing what the MCAP recorder writes, as it writes it.

    Call it as the recorder's mirror (:data:`pipeline.record.mcap_log.MessageMirror`): one
    channel per topic, with the MCAP's schema. The static topics (``/tf``, the camera
    calibrations) are written once at the start: each is sent again to every client
    that subscribes to it later.
    """

    def __init__(self, host: str, port: int, *, name: str) -> None:
        import foxglove

        if not log.isEnabledFor(logging.DEBUG):
            # The server's own start and stop lines: the run says where it serves.
            logging.getLogger("foxglove").setLevel(logging.WARNING)
        self._foxglove = foxglove
        server = self

        class Listener(foxglove.ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                with server._lock:  # the SDK calls from its own threads, one per client
                    server.subscribed += 1
                server.resend_static(channel.topic)

            def on_unsubscribe(self, client: Any, channel: Any) -> None:
                with server._lock:
                    server.subscribed -= 1

        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._statics: dict[str, tuple[bytes, int]] = {}
        self._lock = threading.Lock()
        self.subscribed = 0  # subscriptions open now, of every client
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context, server_listener=Listener()
            )
        except Exception as exc:  # the SDK's error for a port in use or an unknown host
            raise SettingsError(
                f"--foxglove {host}:{port}: cannot serve there ({' '.join(str(exc).split())[:160]}); "
                "choose another HOST:PORT"
            ) from None
        self.address = f"ws://{f'[{host}]' if ':' in host else host}:{self._server.port}"  # IPv6 in brackets

    def __call__(self, topic: str, schema: ChannelSchema, data: bytes, time_ns: int) -> None:
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._foxglove.Channel(
                    topic,
                    schema=self._foxglove.Schema(
                        name=schema.name, encoding=schema.encoding, data=schema.data
                    ),
                    message_encoding=schema.message_encoding,
                    context=self._context,
                )
                self._channels[topic] = channel
            if _is_static(topic):
                self._statics[topic] = (data, time_ns)
        channel.log(data, log_time=time_ns)

    def resend_static(self, topic: str) -> None:
        """A client subscribed to ``topic``: a static topic's message goes out again for it."""
        with self._lock:
            static = self._statics.get(topic)
            target = self._channels.get(topic)
        if static is not None and target is not None:
            target.log(static[0], log_time=static[1])

    def stop(self) -> None:
        """Close the server, after ``DRAIN_S`` for its subscribers' queues to go out, waiting
        at most ``STOP_TIMEOUT_S`` for its clients: the SDK's stop waits for each to close, and
        a client that stopped reading (a stalled network, a frozen app) would hold the run (and
        its signals: the wait is in native code) until it goes. Past the wait the server is
        left to the process' exit, with a warning."""
        if self.subscribed > 0:
            time.sleep(DRAIN_S)
        closing = threading.Thread(target=self._server.stop, name="foxglove-stop", daemon=True)
        closing.start()
        closing.join(STOP_TIMEOUT_S)
        if closing.is_alive():
            log.warning(
                "Foxglove: a client did not close within %g s (it stopped reading?); left to the exit",
                STOP_TIMEOUT_S,
            )


def _is_static(topic: str) -> bool:
    return topic == TF_TOPIC or topic.endswith("/calibration")
