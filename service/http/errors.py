"""The service's error type and the handlers that turn every failure into a JSON error body.

A client mistake is answered with its 4xx code and a message saying what was expected; nothing a
client sends can produce a 500. Every error body has the shape of :class:`service.schemas.ErrorBody`.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from service.http.error_types import ERROR_TYPES

log = logging.getLogger(__name__)



class ApiError(Exception):
    """An error answered with ``status``; ``extra`` fields are added to the body, ``headers`` to the response."""

    def __init__(self, status: int, message: str, *, error: str | None = None, headers: dict[str, str] | None = None,
                 **extra: Any) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.error = error or ERROR_TYPES.get(status, "error")
        self.headers = headers or {}
        self.extra = extra


def error_response(status: int, message: str, *, error: str | None = None, headers: dict[str, str] | None = None,
                   **extra: Any) -> JSONResponse:
    """The JSON error body every handler answers with."""
    body = {"error": error or ERROR_TYPES.get(status, "error"), "detail": message, **extra}
    # nosniff here too: a 500 is answered outside the app's middleware (service.http.security_headers)
    return JSONResponse(body, status_code=status, headers={"X-Content-Type-Options": "nosniff", **(headers or {})})


async def _api_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return error_response(exc.status, exc.message, error=exc.error, headers=exc.headers, **exc.extra)


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    if exc.status_code == 413:
        limit = request.scope.get("starlette.max_body_size")
        message = f"request body is larger than the limit of {limit} bytes" if limit else message
    return error_response(exc.status_code, message, headers=dict(exc.headers or {}))


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    problems = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "")} for e in exc.errors()]
    message = "; ".join(f"{'.'.join(str(p) for p in item['loc'])}: {item['msg']}" for item in problems)
    return error_response(422, message or "invalid request", error="invalid_parameters", problems=problems)


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return error_response(500, "internal error (logged on the server)")


def install_error_handlers(app: FastAPI) -> None:
    """Route ApiError, HTTP errors (404, 405, 413 from the body limit) and parameter validation to JSON bodies."""
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected_error)


class DeclaredBodyLimit:
    """Answers a JSON 413 at once when ``Content-Length`` announces more than ``max_body_size`` bytes.

    FastAPI's ``max_body_size`` (set on the segment route) enforces the limit on the bytes actually read, also for
    chunked bodies; for a declared oversize it would answer plain text, so this guard, placed in front,
    gives that case the same JSON error body as every other error.
    """

    def __init__(self, app: ASGIApp, max_body_size: int) -> None:
        self.app = app
        self.max_body_size = max_body_size

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            declared = Headers(scope=scope).get("content-length")
            # a digit string longer than the limit's is over it (and int() of 4,300+ digits would raise)
            if declared is not None and declared.isascii() and declared.isdigit() and (
                    len(declared.lstrip("0")) > len(str(self.max_body_size)) or int(declared) > self.max_body_size):
                response = error_response(413, f"request body of {declared[:24]} bytes is larger than the limit of "
                                               f"{self.max_body_size} bytes", headers={"Connection": "close"})
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)
