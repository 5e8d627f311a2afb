"""The ASGI app ``python -m service`` runs: it answers at once and becomes the service's app once that is
built, so that the port answers within seconds of the start instead of after every import and model.

Importing the service (torch, the models) takes seconds and loading the models tens of seconds. Until the app is
built (its module imported on a thread), ``/healthz`` answers 200, ``/readyz`` 503 ``loading`` (progress:
``importing the service``) and every other path 503 ``not_ready`` with Retry-After, in the service's JSON shapes;
then the app's own lifespan starts (it loads the models in the background: ``/readyz`` shows each model's stage)
and every request goes to it. Nothing here imports torch.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger(__name__)


class StartingApp:
    """Answers health and readiness while ``build()`` (run on a thread) makes the real app, then forwards to it
    and runs its lifespan inside this one's. ``on_built(app)`` is called once the app exists."""

    def __init__(self, build: Callable[[], ASGIApp], *, retry_after_s: int = 1,
                 on_built: Callable[[ASGIApp], None] | None = None) -> None:
        self.build = build
        self.retry_after_s = retry_after_s
        self.on_built = on_built
        self.app: ASGIApp | None = None
        self.error: str | None = None
        self._lifespan: asyncio.Task | None = None
        self._to_app: asyncio.Queue[Message] = asyncio.Queue()
        self._from_app: asyncio.Queue[Message] = asyncio.Queue()
        self._starting: asyncio.Task | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            await self._run_lifespan(receive, send)
        elif self.app is not None:
            await self.app(scope, receive, send)
        elif scope["type"] == "http":
            await self._answer_while_starting(scope, send)

    async def _run_lifespan(self, receive: Receive, send: Send) -> None:
        message = await receive()
        assert message["type"] == "lifespan.startup"
        self._starting = asyncio.create_task(self._start())
        await send({"type": "lifespan.startup.complete"})
        message = await receive()
        assert message["type"] == "lifespan.shutdown"
        if self._starting is not None and not self._starting.done():
            await asyncio.wait([self._starting])
        if self._lifespan is not None:
            await self._to_app.put({"type": "lifespan.shutdown"})
            await self._from_app.get()
            await self._lifespan
        await send({"type": "lifespan.shutdown.complete"})

    async def _start(self) -> None:
        start = time.perf_counter()
        log.info("importing the service and building its app")
        try:
            app = await asyncio.to_thread(self.build)
        except Exception as exc:  # noqa: BLE001 (reported by /readyz and the log; the process keeps answering)
            self.error = f"the service could not be built: {type(exc).__name__}: {exc}"
            log.exception("the service could not be built")
            return
        log.info("service app built in %.1f s; starting it (the models load in the background)",
                 time.perf_counter() - start)
        self._lifespan = asyncio.create_task(app({"type": "lifespan", "asgi": {"version": "3.0"}, "state": {}},
                                                 self._to_app.get, self._from_app.put))
        await self._to_app.put({"type": "lifespan.startup"})
        answer = await self._from_app.get()
        if answer["type"] != "lifespan.startup.complete":
            self.error = f"the service did not start: {answer.get('message', answer['type'])}"
            log.error(self.error)
            return
        if self.on_built is not None:
            self.on_built(app)
        self.app = app

    async def _answer_while_starting(self, scope: Scope, send: Send) -> None:
        path = scope.get("path", "")
        if path == "/healthz":
            status, body = 200, {"status": "ok"}
        elif path == "/readyz":
            status, body = 503, {"ready": False, "status": "loading" if self.error is None else "not_ready",
                                 "progress": {"service": self.error or "importing the service"}, "models": {},
                                 "ledger": "not opened yet"}
        else:
            status, body = 503, {"error": "not_ready", "detail": self.error or "the service is starting; try again "
                                                                              "in a few seconds"}
        headers = [(b"content-type", b"application/json"), (b"x-content-type-options", b"nosniff")]
        if status != 200:
            headers.append((b"retry-after", str(self.retry_after_s).encode()))
        payload = json.dumps(body).encode()
        headers.append((b"content-length", str(len(payload)).encode()))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": payload})
