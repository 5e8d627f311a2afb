"""The ``error`` field of each HTTP status the service answers with (its own module: ``service.server.http_server``
answers refusals with it before the app, and FastAPI, have been imported)."""

ERROR_TYPES = {
    400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
    408: "request_timeout", 409: "conflict", 413: "content_too_large", 415: "unsupported_media_type",
    422: "unprocessable", 429: "quota_exceeded", 431: "headers_too_large", 500: "internal_error", 503: "unavailable",
}
