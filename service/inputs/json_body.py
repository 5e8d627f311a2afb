"""Small JSON request bodies (``POST /v1/streams``), read by the route after the caller is authenticated.

FastAPI reads a ``Body()`` parameter before it resolves any dependency, so a route declaring one read (and parsed)
whatever a keyless client sent before answering 401. Routes that take JSON therefore declare no body parameter and
call :func:`read_json` once their ``Caller`` is known: the body is bounded by ``max_json_body_bytes`` (413 for a
declared length beyond it at once, for a chunked body as soon as the bytes pass it), held in the upload gate like
any upload (per tenant and in total), paced like a cube, and validated against its pydantic model (422).
"""

from __future__ import annotations

from typing import Any, TypeVar

from fastapi import Request
from pydantic import BaseModel, ValidationError
from starlette.requests import ClientDisconnect

from service.http.errors import ApiError
from service.inputs.upload import UploadGate, paced
from service.settings import Settings

M = TypeVar("M", bound=BaseModel)
MAX_LENGTH_DIGITS = 19  # a Content-Length beyond 2**63 is no length any client sends


def declared_length(request: Request) -> int | None:
    """The request's Content-Length (None when chunked); 400 for a malformed one."""
    value = request.headers.get("content-length")
    if value is None:
        return None
    if not (value.isascii() and value.isdigit()) or len(value) > MAX_LENGTH_DIGITS:
        raise ApiError(400, f"invalid Content-Length {value[:32]!r}: expected at most {MAX_LENGTH_DIGITS} digits")
    return int(value)


def _too_large(limit: int, what: str) -> ApiError:
    return ApiError(413, f"JSON body {what} is larger than the limit of {limit} bytes (max_json_body_bytes)",
                    headers={"Connection": "close"})


async def read_json(request: Request, settings: Settings, uploads: UploadGate, tenant: str,
                    model: type[M]) -> M | None:
    """The request's JSON body as ``model`` (None for an empty body); 413 past ``max_json_body_bytes``, 415 for a
    body that is not ``application/json``, 422 for one that does not validate, 503 when the upload gate is full."""
    limit = settings.max_json_body_bytes
    length = declared_length(request)
    if length is not None and length > limit:
        raise _too_large(limit, f"of {length} bytes")
    if length == 0 or (length is None and "chunked" not in request.headers.get("transfer-encoding", "").lower()):
        return None
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type != "application/json":
        raise ApiError(415, f"content type {media_type or '(none)'!r} is not accepted: send application/json")
    data = bytearray()
    with uploads.admit(tenant, length) as ticket:
        try:
            async for chunk in paced(request.stream(), settings):
                data += chunk
                if len(data) > limit:
                    raise _too_large(limit, f"of more than {limit} bytes")
                if length is None:
                    ticket.charge(max(ticket.bytes, len(data)))
        except ClientDisconnect:
            raise ApiError(400, "client disconnected before sending the whole body") from None
    if not data.strip():
        return None
    try:
        return model.model_validate_json(bytes(data))
    except ValidationError as exc:
        problems: list[dict[str, Any]] = [{"loc": ["body", *e.get("loc", ())], "msg": e.get("msg", "")}
                                          for e in exc.errors()]
        message = "; ".join(f"{'.'.join(str(p) for p in item['loc'])}: {item['msg']}" for item in problems)
        raise ApiError(422, message or "invalid JSON body", error="invalid_parameters", problems=problems) from None


def json_request_body(model: type[BaseModel], description: str) -> dict[str, Any]:
    """``openapi_extra`` documenting an optional JSON body of ``model`` (the route reads it itself)."""
    return {"requestBody": {"required": False, "description": description,
                            "content": {"application/json": {"schema": model.model_json_schema()}}}}
