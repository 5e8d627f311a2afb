"""OpenAPI descriptions of the error answers, shared by the routers."""

from __future__ import annotations

from typing import Any

from service.schemas import ErrorBody, QuotaErrorBody

ERROR_DESCRIPTIONS: dict[int, tuple[type, str]] = {
    400: (ErrorBody, "Malformed request: a body that is not a .npy file, a pickled/object array, a byte count "
                     "that does not match its header; a header that is not valid JSON or nested too deep; "
                     "ambiguous credentials (two keys, or a key beside another Authorization)"),
    401: (ErrorBody, "Missing or unknown API key (when keys are configured)"),
    403: (ErrorBody, "The key is valid but not allowed to do this (another tenant's usage needs an admin key)"),
    404: (ErrorBody, "No such stream for this tenant: never opened, closed, expired (unused for stream_idle_s) or "
                     "another tenant's"),
    408: (ErrorBody, "The body fell behind the minimum upload rate or missed the upload deadline (the "
                     "connection is closed)"),
    409: (ErrorBody, "A frame of the stream that is not after its last frame (?seq= repeated or older), or "
                     "another frame of the stream in flight (Retry-After)"),
    413: (ErrorBody, "Body larger than the configured limit (max_body_bytes), or a declared length larger than any "
                     "cube the model takes (answered before the body is read)"),
    415: (ErrorBody, "Content type is not application/x-npy or application/octet-stream"),
    422: (ErrorBody, "Valid .npy but not what the model takes (shape, dtype, NaN/Inf, values beyond the "
                     "float32 range of the transform; the message says what it expects), an unknown model, or "
                     "invalid query parameters"),
    429: (QuotaErrorBody, "The tenant's daily MAC quota does not cover the request (Retry-After: seconds until "
                          "its requests in flight end, or until the next UTC day when the quota is spent); for "
                          "POST /v1/streams, the tenant's cap on open streams (error too_many_streams)"),
    503: (ErrorBody, "Not ready (model or ledger unavailable), saturated (every slot of the model is taken) or "
                     "too many uploads in progress (in total or of the tenant); Retry-After says when to try again"),
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The ``responses=`` entry of a route for these error codes."""
    return {code: {"model": ERROR_DESCRIPTIONS[code][0], "description": ERROR_DESCRIPTIONS[code][1]}
            for code in codes}
