"""The live view's server: the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``,
the framing of Foxglove's ws-protocol v1) on one port, behind an Origin gate (``websockets``).

A browser sends the page's ``Origin`` with every WebSocket handshake, and a server that takes
any Origin lets any web page opened on the machine read the overlay and the pose.
foxglove-sdk's own server has no hook for the handshake, and relaying to it leaves a second
port that takes any Origin, so the protocol is served here: foxglove-sdk still encodes every
message and gives its schema (``perchpose.io.view``), this module only frames and routes them.

The handshake: a connection without an Origin (a native app, a script) or from an allowed one
(``ALLOWED_ORIGINS``, plus those the user names) is served; any other is refused with HTTP 403,
and a client that does not speak ``foxglove.sdk.v1`` with HTTP 400, each said once with the
reason. Then, as the protocol has it: ``serverInfo`` and ``advertise`` (JSON), the client's
``subscribe`` and ``unsubscribe``, and each logged message to every subscription of its channel
as a binary ``messageData`` frame (opcode 1, subscription id as ``uint32``, log time in ns as
``uint64``, both little-endian, then the payload). Anything else the client sends is answered
with a ``status`` error. A client that reads slower than messages come keeps the newest
``backlog`` messages; the older are dropped and counted.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import contextlib
import json
import logging
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from http import HTTPStatus
from typing import Any

from perchpose.errors import PerchposeError

log = logging.getLogger(__name__)

SUBPROTOCOL = "foxglove.sdk.v1"
ALLOWED_ORIGINS = ("https://app.foxglove.dev",)  # the Foxglove web app
MESSAGE_DATA = 1  # the binary opcode of a message to a subscription
STATUS_ERROR = 2


def _websockets() -> Any:
    try:
        from websockets.asyncio.server import serve
    except ImportError as exc:
        raise PerchposeError('the live view needs websockets: pip install -e ".[view]"') from exc
    return serve


@dataclass(frozen=True)
class ViewChannel:
    """One advertised channel: ``encoding`` ``protobuf`` (``schema`` a serialized
    FileDescriptorSet) or ``json`` (``schema`` a JSON Schema's text)."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: bytes

    def advertisement(self) -> dict[str, Any]:
        protobuf = self.encoding == "protobuf"
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.schema_name,
            "schemaEncoding": "protobuf" if protobuf else "jsonschema",
            "schema": (
                base64.b64encode(self.schema).decode("ascii")
                if protobuf
                else self.schema.decode("utf-8")
            ),
        }


@dataclass(eq=False)
class _Client:
    """A served connection: its subscriptions (id -> channel id) and its outgoing frames."""

    connection: Any
    backlog: int
    subscriptions: dict[int, int] = field(default_factory=dict)
    outgoing: collections.deque[bytes | str] = field(default_factory=collections.deque)
    ready: asyncio.Event = field(default_factory=asyncio.Event)

    def put(self, frame: bytes | str) -> bool:
        """Queue a frame; whether the oldest message was dropped for it (the JSON control
        frames are never dropped)."""
        oldest = None
        if len(self.outgoing) >= self.backlog:
            oldest = next((f for f in self.outgoing if isinstance(f, bytes)), None)
            if oldest is not None:
                self.outgoing.remove(oldest)
        self.outgoing.append(frame)
        self.ready.set()
        return oldest is not None

    async def drain(self) -> None:
        """Send what is queued as it comes, until the connection closes."""
        with contextlib.suppress(Exception):  # a closed connection ends only its sender
            while True:
                await self.ready.wait()
                self.ready.clear()
                while self.outgoing:
                    await self.connection.send(self.outgoing.popleft())


class FoxgloveServer:
    """Serves ``channels`` on ``host:port`` (0: a free port, ``self.port`` says which) from a
    thread of its own; ``log`` (from any thread) sends a message to the channel's
    subscribers. ``report`` says each refused handshake once; ``refused`` counts them."""

    def __init__(
        self,
        host: str,
        port: int,
        channels: Sequence[ViewChannel],
        name: str = "perchpose",
        allowed_origins: tuple[str, ...] = (),
        report: Callable[[str], None] | None = None,
        backlog: int = 64,
    ) -> None:
        serve = _websockets()
        self.name = name
        self.channels = {channel.id: channel for channel in channels}
        self.allowed = {origin.rstrip("/") for origin in (*ALLOWED_ORIGINS, *allowed_origins)}
        self.report = report or log.warning
        self.backlog = backlog
        self.refused = 0
        self.dropped = 0
        self.session_id = str(time.time_ns())
        self._said: set[str] = set()
        self._clients: set[_Client] = set()
        self._subscribers: dict[int, int] = {}  # channel id -> subscriptions to it
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(
                self._start(serve, host, port), self._loop
            ).result(timeout=10)
        except Exception as exc:  # a port in use, a host that is not ours
            self._stop_loop()
            raise PerchposeError(f"--view: cannot serve on {host}:{port} ({exc})") from exc
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _start(self, serve: Any, host: str, port: int) -> Any:
        return await serve(
            self._serve_client,
            host,
            port,
            process_request=self._check,
            subprotocols=[SUBPROTOCOL],
            max_size=2**20,
            compression=None,
        )

    def subscribed(self, channel_id: int) -> bool:
        """Whether any client subscribes to the channel now (to skip encoding otherwise)."""
        return self._subscribers.get(channel_id, 0) > 0

    def log(self, channel_id: int, payload: bytes, log_time_ns: int) -> None:
        """Send ``payload`` (already encoded) to every subscription of the channel."""
        if self.subscribed(channel_id):
            self._loop.call_soon_threadsafe(self._dispatch, channel_id, payload, log_time_ns)

    def _dispatch(self, channel_id: int, payload: bytes, log_time_ns: int) -> None:
        for client in self._clients:
            for subscription, channel in client.subscriptions.items():
                if channel == channel_id:
                    header = struct.pack("<BIQ", MESSAGE_DATA, subscription, log_time_ns)
                    self.dropped += int(client.put(header + payload))

    def _refuse(self, connection: Any, status: HTTPStatus, key: str, why: str) -> Any:
        self.refused += 1
        if key not in self._said:
            self._said.add(key)
            self.report(f"live view: refused a connection: {why} (said once)")
        return connection.respond(status, f"{why}\n")

    def _check(self, connection: Any, request: Any) -> Any:
        """The handshake: None lets it through; a response refuses it."""
        origin = request.headers.get("Origin")
        if origin is not None and origin.rstrip("/") not in self.allowed:
            return self._refuse(
                connection,
                HTTPStatus.FORBIDDEN,
                f"origin {origin}",
                f"Origin {origin} is not allowed (--view-origin {origin} allows it)",
            )
        offered = [
            p.strip()
            for value in request.headers.get_all("Sec-WebSocket-Protocol")
            for p in value.split(",")
        ]
        if SUBPROTOCOL not in offered:
            return self._refuse(
                connection,
                HTTPStatus.BAD_REQUEST,
                f"protocol {offered}",
                f"the client offers {', '.join(offered) or 'no subprotocol'}, not "
                f"{SUBPROTOCOL} (Foxglove, or Lichtblick from the release that added it)",
            )
        return None

    async def _serve_client(self, connection: Any) -> None:
        client = _Client(connection, self.backlog)
        self._clients.add(client)
        client.put(
            json.dumps(
                {
                    "op": "serverInfo",
                    "name": self.name,
                    "capabilities": [],
                    "metadata": {},
                    "sessionId": self.session_id,
                }
            )
        )
        channels = [channel.advertisement() for channel in self.channels.values()]
        client.put(json.dumps({"op": "advertise", "channels": channels}))
        sender = asyncio.create_task(client.drain())
        try:
            async for message in connection:
                self._handle(client, message)
        except Exception as exc:  # a connection that breaks ends only itself
            log.debug("live view client: %s", exc)
        finally:
            sender.cancel()
            self._clients.discard(client)
            for channel in client.subscriptions.values():
                self._subscribers[channel] -= 1

    def _handle(self, client: _Client, message: bytes | str) -> None:
        """A client's message: subscribe and unsubscribe are served, anything else is
        answered with a status error."""
        try:
            if isinstance(message, bytes):
                raise ValueError("binary client messages are not taken (no clientPublish)")
            request = json.loads(message)
            op = request.get("op") if isinstance(request, dict) else None
            if op == "subscribe":
                for item in request["subscriptions"]:
                    subscription, channel = int(item["id"]), int(item["channelId"])
                    if channel not in self.channels:
                        raise ValueError(f"no channel {channel}")
                    if subscription in client.subscriptions:
                        raise ValueError(f"subscription {subscription} is taken")
                    client.subscriptions[subscription] = channel
                    self._subscribers[channel] = self._subscribers.get(channel, 0) + 1
            elif op == "unsubscribe":
                for subscription in request["subscriptionIds"]:
                    if int(subscription) in client.subscriptions:
                        channel = client.subscriptions.pop(int(subscription))
                        self._subscribers[channel] -= 1
            else:
                raise ValueError(f"op {op!r} is not served (subscribe, unsubscribe)")
        except (ValueError, KeyError, TypeError) as exc:
            status = {"op": "status", "level": STATUS_ERROR, "message": f"Invalid message: {exc}"}
            client.put(json.dumps(status))

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)

    def close(self) -> None:
        """Stop serving and close every connection."""

        async def shutdown() -> None:
            self._server.close()
            await self._server.wait_closed()

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(timeout=5)
        self._stop_loop()
