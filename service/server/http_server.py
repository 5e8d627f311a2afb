"""The service under uvicorn with the HTTP limits of its settings: what ``python -m service`` (and
``radarseg serve``) runs.

What an ASGI app cannot do itself, because it happens before a request reaches it, is done here:

- the port is bound and listening before the models load (they load in the app's background, ``/readyz`` says
  how far), so a second server on a busy port fails at once (exit 2) and ``/healthz`` answers within seconds;
- every connection that makes no progress toward a complete request is closed after a bounded time, whatever
  it sent before and whether or not it has a key: a request head must be complete within ``header_timeout_s``
  of its first byte, of the connection, or of the previous answer (408; arriving bytes never restart that
  clock), an idle connection between requests is closed after ``keep_alive_s`` (uvicorn's own
  ``timeout_keep_alive``), a body is paced by the app (``service.inputs.upload.paced``), and a connection whose request
  was answered before its body arrived (``GET /healthz`` announcing a megabyte) is closed after the answer;
- at most ``max_connections`` connections are open (the file limit bounds them anyway: see
  :func:`connection_cap`); a new one beyond closes the connection that has waited longest for a request head,
  or is answered 503 when every connection is busy with a request. (uvicorn's ``limit_concurrency`` answers
  503 only once a head has arrived and never closes a quiet socket, so it cannot keep descriptors free);
- the request head is bounded: more than ``max_header_bytes`` of request line and headers, or more than
  ``max_headers`` headers, is answered 431 (a request line alone over the bound: 414) as soon as the bound
  is passed, without buffering the rest (uvicorn's httptools parser has no such bound: one 32 MiB header was
  accepted and raised the RSS by 48 MiB);
- malformed HTTP (a bad or duplicated Content-Length, Content-Length beside chunked, a bad chunk size) is
  answered in the service's JSON error shape instead of uvicorn's text/plain 400;
- every refusal made here is counted in ``/metrics`` (``radarseg_server_refusals_total{reason}``).

Closing is lingering: our side is shut for writing at once, what the client still sends is read and dropped
for ``linger_s``, then the socket closes (closing at once with unread input would reset the connection, and
the client could lose the answer).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import resource
import socket
import sys
import time
from typing import Any

import httptools
import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.http.error_types import ERROR_TYPES
from service.http.public_text import EscapeControlCharacters
from service.server.starting_app import StartingApp
from service.settings import Settings

log = logging.getLogger(__name__)

FILE_RESERVE = 64  # descriptors kept for what is not a connection: ledger, checkpoints, logs, the listening socket
DEFAULT_MAX_CONNECTIONS = 4096
REASONS = {400: b"Bad Request", 408: b"Request Timeout", 414: b"URI Too Long", 431: b"Request Header Fields Too Large",
           503: b"Service Unavailable"}
REFUSAL_LABELS = {400: "malformed_http", 408: "header_timeout", 414: "target_too_long", 431: "head_too_large",
                  503: "connection_cap"}


class RefusalCounter:
    """What the protocol counts its refusals in: ``count(reason)`` (the app's metrics once the app is built)."""

    def __init__(self) -> None:
        self.counter: Any = None

    def count(self, reason: str) -> None:
        if self.counter is not None:
            self.counter.labels(reason).inc()


class LingeringTransport:
    """The connection's transport as the protocol and uvicorn see it: ``close()`` shuts our side for writing, drops
    what still arrives for ``linger_s`` and then closes (uvicorn closes at once after a ``Connection: close``
    answer, which resets a client still sending its body before it reads the answer)."""

    def __init__(self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop, linger_s: float) -> None:
        self._transport = transport
        self._loop = loop
        self._linger_s = linger_s
        self.lingering = False

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)

    def is_closing(self) -> bool:
        return self.lingering or self._transport.is_closing()

    def close(self) -> None:
        if self.is_closing():
            return
        self.lingering = True
        if self._transport.can_write_eof():
            self._transport.write_eof()
            self._transport.resume_reading()
            self._loop.call_later(self._linger_s, self._transport.close)
        else:
            self._transport.close()

    def abort(self) -> None:
        self.lingering = True
        self._transport.abort()


class HeadRefused(Exception):
    """The request head passed a bound; ``status`` and ``detail`` are what the client is answered."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


def _cancelled(timer: asyncio.TimerHandle | None) -> None:
    """Cancel ``timer`` if there is one; what its holder keeps instead (None)."""
    if timer is not None:
        timer.cancel()


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with bounded request heads, bounded connections, lingering closes and JSON
    answers to malformed requests. The limits are set on the subclass :func:`guarded_protocol` builds."""

    max_header_bytes = 65536
    max_headers = 100
    header_timeout_s = 30.0
    max_connections = DEFAULT_MAX_CONNECTIONS
    linger_s = 2.0  # after refusing, read and drop what the client still sends for this long before closing
    write_timeout_s = 60.0  # an answer the client stops taking must be taken within this from that moment
    refusals = RefusalCounter()

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003 (uvicorn's signature)
        super().__init__(*args, **kwargs)
        self._reading_head = True
        self._head_since = time.monotonic()  # when this connection began waiting for its current request head
        self._head_bytes = 0  # bytes received since this request began, while its head is incomplete
        self._head_content = 0  # request line and header bytes parsed so far
        self._header_count = 0
        self._url_bytes = 0
        self._refused = False
        self._head_timer: asyncio.TimerHandle | None = None
        self._write_timer: asyncio.TimerHandle | None = None

    def pause_writing(self) -> None:
        """The client stopped taking the answer (the transport's buffer is full): its deadline starts now."""
        super().pause_writing()
        if self._write_timer is None:
            self._write_timer = self.loop.call_later(self.write_timeout_s, self._write_timed_out)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self.cycle is None or self.cycle.response_complete:  # the whole answer left the buffer's high mark
            self._cancel_write_timer()

    def _cancel_write_timer(self) -> None:
        self._write_timer = _cancelled(self._write_timer)

    def _write_timed_out(self) -> None:
        self._write_timer = None
        self.refusals.count("write_timeout")
        self.transport.abort()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.transport = LingeringTransport(transport, self.loop, self.linger_s)  # type: ignore[assignment]
        self._arm_head_timer()
        if len(self.connections) > self.max_connections:
            self._make_room()

    def _make_room(self) -> None:
        """Over the cap: close the connection that has waited longest for a request head (idle keep-alive, a
        stalled head), or refuse this one with 503 when every other connection is busy with a request."""
        waiting = [c for c in self.connections if c is not self and isinstance(c, GuardedHttpToolsProtocol)
                   and c._awaiting_head() and not c.transport.is_closing()]
        if waiting:
            oldest = min(waiting, key=lambda c: c._head_since)
            self.refusals.count("connection_evicted")
            oldest._cancel_head_timer()
            oldest.transport.close()
        else:
            self._refuse(503, f"every one of the {self.max_connections} connections is busy with a request")

    def _awaiting_head(self) -> bool:
        return self._reading_head and (self.cycle is None or self.cycle.response_complete)

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        self._cancel_write_timer()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_since = time.monotonic()
            self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_timed_out)

    def _cancel_head_timer(self) -> None:
        self._head_timer = _cancelled(self._head_timer)

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self._awaiting_head():
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

    def on_response_complete(self) -> None:
        cycle = self.cycle
        unfinished = cycle is not None and cycle.more_body and not cycle.disconnected
        super().on_response_complete()
        if self.transport.is_closing():
            return
        if unfinished:
            # answered before its body arrived (a route that reads no body): the rest of that body is no request,
            # and waiting for it would let the client hold the connection byte by byte: close
            self._unset_keepalive_if_required()
            self.transport.close()
        elif self.cycle is cycle:  # no pipelined request started: the next head is due within header_timeout_s
            self._reading_head = True
            self._head_bytes = 0
            self._arm_head_timer()

    def data_received(self, data: bytes) -> None:
        if self._refused or self.transport.is_closing():  # lingering: the rest is dropped unread
            return
        if self._reading_head:
            self._head_bytes += len(data)
        self._unset_keepalive_if_required()  # bytes end the idle wait; the head timer keeps running
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
        """Answer ``status`` with a JSON error body and close the connection (lingering), counted by reason."""
        if self.transport.is_closing() or self._refused:
            return
        self._refused = True
        self._cancel_head_timer()
        self.refusals.count(REFUSAL_LABELS[status])
        if self.cycle is not None and not self.cycle.response_complete:
            # a request whose body turned out malformed: its app sees a disconnect and sends nothing more
            self.cycle.disconnected = True
            self.cycle.message_event.set()
        body = json.dumps({"error": ERROR_TYPES.get(status, "bad_request"), "detail": detail}).encode()
        retry = b"retry-after: 1\r\n" if status == 503 else b""
        self.transport.write(b"".join([
            b"HTTP/1.1 %d %s\r\n" % (status, REASONS[status]),
            *[name + b": " + value + b"\r\n" for name, value in self.server_state.default_headers],
            b"content-type: application/json\r\nx-content-type-options: nosniff\r\ncontent-length: %d\r\n"
            b"%sconnection: close\r\n\r\n" % (len(body), retry), body]))
        self.transport.close()


def connection_cap(settings: Settings) -> int:
    """The most connections this process keeps open. Each takes a file descriptor, so the cap must stay below
    the file limit (RLIMIT_NOFILE) less FILE_RESERVE: the soft limit is raised toward the hard one when that is
    needed and allowed; a configured ``max_connections`` that still does not fit is lowered (with a warning)."""
    wanted = settings.max_connections or DEFAULT_MAX_CONNECTIONS
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = wanted + FILE_RESERVE
    if soft != resource.RLIM_INFINITY and soft < needed:
        target = needed if hard == resource.RLIM_INFINITY else min(hard, needed)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    fits = wanted if soft == resource.RLIM_INFINITY else max(2, min(wanted, soft - FILE_RESERVE))
    if settings.max_connections is not None and fits < wanted:
        log.warning("max_connections %d does not fit the file limit %d (less %d reserved): %d connections at most",
                    wanted, soft, FILE_RESERVE, fits)
    return fits


def guarded_protocol(settings: Settings, refusals: RefusalCounter | None = None) -> type[GuardedHttpToolsProtocol]:
    """The protocol class with this service's head and connection limits."""
    return type("ServiceHttpProtocol", (GuardedHttpToolsProtocol,),
                {"max_header_bytes": settings.max_header_bytes, "max_headers": settings.max_headers,
                 "header_timeout_s": settings.header_timeout_s, "max_connections": connection_cap(settings),
                 "write_timeout_s": settings.write_timeout_s,
                 "refusals": refusals or RefusalCounter()})


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
    """``python -m service`` on ``port`` with this interpreter (settings from RADARSEG_*)."""
    return [sys.executable, "-m", "service", "--port", str(port), "--log-level", log_level]


def serve(settings: Settings, *, log_level: str = "info") -> None:
    """Bind the port and answer on it at once; the app is built (imports) on a thread and loads its models in the
    background (``service.server.starting_app``); run until stopped."""
    sock = bind(settings.host, settings.port)
    refusals = RefusalCounter()

    def build() -> Any:
        from service.main import create_app

        return create_app(settings, load_in_background=True)

    def built(app: Any) -> None:
        refusals.counter = app.state.service.metrics.server_refusals

    protocol = guarded_protocol(settings, refusals)
    log.info("serving on %s:%d (at most %d connections); importing the service", settings.host, settings.port,
             protocol.max_connections)
    app = StartingApp(build, retry_after_s=settings.retry_after_s, on_built=built)
    config = uvicorn.Config(app, http=protocol, host=settings.host, port=settings.port, log_level=log_level,
                            timeout_keep_alive=settings.keep_alive_s)  # type: ignore[arg-type]
    uvicorn.Server(config).run(sockets=[sock])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service", description=__doc__.split("\n")[0])
    parser.add_argument("--host", help="bind address (default 127.0.0.1, or RADARSEG_HOST)")
    parser.add_argument("--port", type=int, help="port (default 8000, or RADARSEG_PORT)")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    args = parser.parse_args(argv)
    overrides = {name: getattr(args, name) for name in ("host", "port") if getattr(args, name) is not None}
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:  # names from radars and checkpoints cannot forge a log line
        handler.addFilter(EscapeControlCharacters())
    try:
        serve(Settings(**overrides), log_level=args.log_level)
    except PortInUse as exc:
        print(f"radarseg serve: error: {exc} (is another server running there?)", file=sys.stderr)
        return 2
    return 0

