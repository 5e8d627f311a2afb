"""``Connection: close`` on an answer given before the request's body was read to its end (a 415, 401 or 429 of
``POST /v1/segment``, ``GET /healthz`` announcing a body): the rest of that body is no request, so the server closes
the connection after the answer (``service.server.http_server``), and the header tells the client so instead of
letting it send its next request into a closing socket."""

from __future__ import annotations

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send


def _announces_body(scope: Scope) -> bool:
    headers = Headers(scope=scope)
    length = headers.get("content-length", "").strip("0 ")
    return bool(length) or "chunked" in headers.get("transfer-encoding", "").lower()


class CloseOnUnreadBody:
    """Pure ASGI middleware: adds ``Connection: close`` to a response that starts before the request body's last
    message has been received."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not _announces_body(scope):
            await self.app(scope, receive, send)
            return
        body_read = False

        async def tracked_receive() -> Message:
            nonlocal body_read
            message = await receive()
            if message["type"] == "http.disconnect" or not message.get("more_body", False):
                body_read = True
            return message

        async def closing_send(message: Message) -> None:
            if message["type"] == "http.response.start" and not body_read:
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"connection"]
                message = {**message, "headers": [*headers, (b"connection", b"close")]}
            await send(message)

        await self.app(scope, tracked_receive, closing_send)
