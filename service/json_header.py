"""JSON carried in a request header, parsed with a nesting bound: ``json.loads`` recurses once per level
(4,000 nested brackets raised RecursionError, a 500), so the depth is counted first, outside strings."""

from __future__ import annotations

import json
from typing import Any

from service.errors import ApiError


def json_depth(text: str) -> int:
    """Deepest bracket nesting of ``text``, ignoring brackets inside JSON strings."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


def load_json_header(name: str, text: str, *, max_depth: int) -> Any:
    """The JSON value of header ``name``; ApiError 400 naming the problem when it is nested deeper than
    ``max_depth`` or is not valid JSON."""
    depth = json_depth(text)
    if depth > max_depth:
        raise ApiError(400, f"{name} is nested {depth} levels deep, at most {max_depth} accepted",
                       error="invalid_header")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ApiError(400, f"{name} is not valid JSON ({exc})", error="invalid_header") from None
