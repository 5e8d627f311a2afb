"""Run the service under uvicorn with the HTTP limits of its settings: ``python -m service.server``.

What an ASGI app cannot do itself, because it happens before a request reaches it, is done here:

- the port is bound before the models load, so a second server on a busy port fails at once (exit 2)
  instead of loading every model first;
- a request head must be complete within ``header_timeout_s`` of its first byte (or of the connection): 408, so that
  a client trickling its headers holds no connection for long (uvicorn times out only idle keep-alive connections);
- the request head is bounded: more than ``max_header_bytes`` of request line and headers, or more than
  ``max_headers`` headers, is answered 431 (a request line alone over the bound: 414) as soon as the bound
  is passed, without buffering the rest (uvicorn's httptools parser has no such bound: one 32 MiB header was
  accepted and raised the RSS by 48 MiB);
- malformed HTTP (a bad or duplicated Content-Length, Content-Length beside chunked, a bad chunk size) is
  answered in the service's JSON error shape instead of uvicorn's text/plain 400.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import socket
import sys

import httptools
import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.errors import ERROR_TYPES
from service.settings import Settings

log = logging.getLogger(__name__)


class HeadRefused(Exception):
    """The request head passed a bound; ``status`` and ``detail`` are what the client is answered."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with bounded request heads and JSON answers to malformed requests.
    ``max_header_bytes`` and ``max_headers`` are set on the subclass :func:`guarded_protocol` builds."""

    max_header_bytes = 65536
    max_headers = 100
    header_timeout_s = 30.0
    linger_s = 2.0  # after refusing, read and drop what the client still sends for this long before closing

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003 (uvicorn's signature)
        super().__init__(*args, **kwargs)
        self._reading_head = True
        self._head_bytes = 0  # bytes received since this request began, while its head is incomplete
        self._head_content = 0  # request line and header bytes parsed so far
        self._header_count = 0
        self._url_bytes = 0
        self._refused = False
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_timed_out)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self._reading_head and (self.cycle is None or self.cycle.response_complete):
            self._refuse(408, f"request head not complete within {self.header_timeout_s:g} s")

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm_head_timer()
        self._reading_head = True
        self._head_content = self._header_count = self._url_bytes = 0

    def on_url(self, url: bytes) -> None:
        self._url_bytes += len(url)
        self._head_content += len(url)
        if self._url_bytes > self.max_header_bytes:
            raise HeadRefused(414, f"request target is longer than {self.max_header_bytes} bytes")
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._header_count += 1
        self._head_content += len(name) + len(value) + 4
        if self._header_count > self.max_headers:
            raise HeadRefused(431, f"more than {self.max_headers} request headers")
        if self._head_content > self.max_header_bytes:
            raise HeadRefused(431, f"request line and headers are larger than {self.max_header_bytes} bytes")
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        self._cancel_head_timer()
        self._reading_head = False
        self._head_bytes = 0
        super().on_headers_complete()

    def data_received(self, data: bytes) -> None:
        if self._refused:  # lingering after a refusal: the rest of the request is dropped unread
            return
        if self._reading_head:
            self._head_bytes += len(data)
        self._unset_keepalive_if_required()
        try:
            self.parser.feed_data(data)
        except httptools.HttpParserUpgrade:
            if self._should_upgrade():
                self.handle_websocket_upgrade()
            else:
                self._unsupported_upgrade_warning()
            return
        except httptools.HttpParserError as exc:
            refused = exc.__context__ if isinstance(exc.__context__, HeadRefused) else None
            if refused is not None:  # raised in a parser callback and wrapped by httptools
                self._refuse(refused.status, refused.detail)
            else:
                self._refuse(400, f"malformed HTTP request ({exc})")
            return
        if self._reading_head and self._head_bytes > self.max_header_bytes + 65536 and self.parser is not None:
            # the head is not complete after this many bytes: it is over the bound whatever comes next
            self._refuse(431, f"request line and headers are larger than {self.max_header_bytes} bytes")

    def send_400_response(self, msg: str) -> None:
        self._refuse(400, f"malformed HTTP request ({msg})")

    def _refuse(self, status: int, detail: str) -> None:
        """Answer ``status`` with a JSON error body and close the connection. The close lingers: our side is shut
        for writing at once, what the client still sends is read and dropped for ``linger_s``, then the socket
        closes (closing at once with unread input would reset the connection, and the client could lose the
        answer)."""
        if self.transport.is_closing() or self._refused:
            return
        self._refused = True
        if self.cycle is not None and not self.cycle.response_complete:
            # a request whose body turned out malformed: its app sees a disconnect and sends nothing more
            self.cycle.disconnected = True
            self.cycle.message_event.set()
        body = json.dumps({"error": ERROR_TYPES.get(status, "bad_request"), "detail": detail}).encode()
        reason = {400: b"Bad Request", 408: b"Request Timeout", 414: b"URI Too Long",
                  431: b"Request Header Fields Too Large"}[status]
        self.transport.write(b"".join([
            b"HTTP/1.1 %d %s\r\n" % (status, reason),
            *[name + b": " + value + b"\r\n" for name, value in self.server_state.default_headers],
            b"content-type: application/json\r\ncontent-length: %d\r\nconnection: close\r\n\r\n" % len(body), body]))
        if self.transport.can_write_eof():
            self.transport.write_eof()
            self.flow.resume_reading()
            self.loop.call_later(self.linger_s, self.transport.close)
        else:
            self.transport.close()


def guarded_protocol(settings: Settings) -> type[GuardedHttpToolsProtocol]:
    """The protocol class with this service's head limits."""
    return type("ServiceHttpProtocol", (GuardedHttpToolsProtocol,),
                {"max_header_bytes": settings.max_header_bytes, "max_headers": settings.max_headers,
                 "header_timeout_s": settings.header_timeout_s})


class PortInUse(OSError):
    """The service's address is taken (by another server, probably another radarseg)."""


def bind(host: str, port: int) -> socket.socket:
    """A socket bound to ``host:port`` (as uvicorn binds it); PortInUse when the address is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise PortInUse(exc.errno, f"cannot bind {host}:{port}: {exc.strerror}") from None
    sock.set_inheritable(True)
    return sock


def server_command(port: int, log_level: str = "warning") -> list[str]:
    """``python -m service.server`` on ``port`` with this interpreter (settings from RADARSEG_*)."""
    return [sys.executable, "-m", "service.server", "--port", str(port), "--log-level", log_level]


def serve(settings: Settings, *, log_level: str = "info") -> None:
    """Bind the port, then build the app and run it (its lifespan loads the models) until stopped."""
    from service.main import create_app

    sock = bind(settings.host, settings.port)
    config = uvicorn.Config(lambda: create_app(settings), factory=True, http=guarded_protocol(settings),
                            host=settings.host, port=settings.port, log_level=log_level)
    uvicorn.Server(config).run(sockets=[sock])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.server", description=__doc__.split("\n")[0])
    parser.add_argument("--host", help="bind address (default 127.0.0.1, or RADARSEG_HOST)")
    parser.add_argument("--port", type=int, help="port (default 8000, or RADARSEG_PORT)")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    args = parser.parse_args(argv)
    overrides = {name: getattr(args, name) for name in ("host", "port") if getattr(args, name) is not None}
    try:
        serve(Settings(**overrides), log_level=args.log_level)
    except PortInUse as exc:
        print(f"radarseg serve: error: {exc} (is another server running there?)", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
