"""The live view's front door: a WebSocket gate (``websockets``) that checks each connection
before relaying it to the Foxglove server (``foxglove-sdk``, listening on loopback only).

A browser sends the page's ``Origin`` with every WebSocket handshake, and a server that takes
any Origin lets any web page open on the machine read the overlay and the pose. foxglove-sdk's
server has no hook for the handshake, so the gate answers it: a connection without an Origin
(a native app, a script) or from an allowed one (``ALLOWED_ORIGINS``, plus those the user
names) is relayed both ways, message for message; any other is refused with HTTP 403, and a
client that does not speak ``foxglove.sdk.v1`` with HTTP 400, each said once with the reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable
from http import HTTPStatus
from typing import Any

from perchpose.errors import PerchposeError

log = logging.getLogger(__name__)

SUBPROTOCOL = "foxglove.sdk.v1"
ALLOWED_ORIGINS = ("https://app.foxglove.dev",)  # the Foxglove web app


def _websockets() -> tuple[Any, Any]:
    try:
        from websockets.asyncio.client import connect
        from websockets.asyncio.server import serve
    except ImportError as exc:
        raise PerchposeError('the live view needs websockets: pip install -e ".[view]"') from exc
    return serve, connect


class OriginGate:
    """Serves ``host:port`` (0: a free port, ``self.port`` says which) and relays each accepted
    connection to the Foxglove server at ``127.0.0.1:upstream_port``."""

    def __init__(
        self,
        host: str,
        port: int,
        upstream_port: int,
        allowed_origins: tuple[str, ...] = (),
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.serve, self.connect = _websockets()
        self.upstream = f"ws://127.0.0.1:{upstream_port}"
        self.allowed = {origin.rstrip("/") for origin in (*ALLOWED_ORIGINS, *allowed_origins)}
        self.report = report or log.warning
        self.refused = 0
        self._said: set[str] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(
                self._start(host, port), self._loop
            ).result(timeout=10)
        except Exception as exc:  # a port in use, a host that is not ours
            self._stop_loop()
            raise PerchposeError(f"--view: cannot serve on {host}:{port} ({exc})") from exc
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _start(self, host: str, port: int) -> Any:
        return await self.serve(
            self._relay,
            host,
            port,
            process_request=self._check,
            subprotocols=[SUBPROTOCOL],
            max_size=None,
            compression=None,
        )

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

    async def _relay(self, client: Any) -> None:
        try:
            async with self.connect(
                self.upstream, subprotocols=[SUBPROTOCOL], max_size=None, compression=None
            ) as server:
                pumps = [
                    asyncio.create_task(self._pump(client, server)),
                    asyncio.create_task(self._pump(server, client)),
                ]
                _, pending = await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for task in pending:
                    task.cancel()
        except (TimeoutError, OSError) as exc:
            log.debug("live view relay: %s", exc)

    @staticmethod
    async def _pump(source: Any, sink: Any) -> None:
        with contextlib.suppress(Exception):  # either side closing ends the relay
            async for message in source:
                await sink.send(message)

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)

    def close(self) -> None:
        """Stop serving and close every relayed connection."""

        async def shutdown() -> None:
            self._server.close()
            await self._server.wait_closed()

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(timeout=5)
        self._stop_loop()
