"""JSON carried in a request header, parsed with bounds on its size, nesting and numbers: ``json.loads``
recurses once per level (4,000 nested brackets raised RecursionError, a 500), so the depth is counted first,
outside strings; an integer of more than 4,300 digits raised Python's ``ValueError`` for integer conversion
(a 500), so number literals are bounded to ``MAX_NUMBER_CHARS`` characters while they are parsed."""

from __future__ import annotations

import json
from typing import Any

from service.http.errors import ApiError

MAX_NUMBER_CHARS = 64  # a number literal (sign, digits, exponent) in a header: far more than any float needs
MAX_HEADER_JSON_BYTES = 8192


class _NumberTooLong(ValueError):
    def __init__(self, literal: str) -> None:
        super().__init__(f"a number of {len(literal)} characters ({literal[:12]}...), at most {MAX_NUMBER_CHARS}")


def _bounded(convert: type) -> Any:
    def parse(literal: str) -> Any:
        if len(literal) > MAX_NUMBER_CHARS:
            raise _NumberTooLong(literal)
        return convert(literal)

    return parse


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


def load_json_header(name: str, text: str, *, max_depth: int, max_bytes: int = MAX_HEADER_JSON_BYTES) -> Any:
    """The JSON value of header ``name``; ApiError 400 naming the problem when it is longer than ``max_bytes``,
    nested deeper than ``max_depth``, holds a number literal longer than ``MAX_NUMBER_CHARS`` or is not valid
    JSON."""
    if len(text) > max_bytes:
        raise ApiError(400, f"{name} is {len(text)} characters long, at most {max_bytes} accepted",
                       error="invalid_header")
    depth = json_depth(text)
    if depth > max_depth:
        raise ApiError(400, f"{name} is nested {depth} levels deep, at most {max_depth} accepted",
                       error="invalid_header")
    try:
        return json.loads(text, parse_int=_bounded(int), parse_float=_bounded(float))
    except _NumberTooLong as exc:
        raise ApiError(400, f"{name} holds {exc}", error="invalid_header") from None
    except ValueError as exc:  # json.JSONDecodeError, and any conversion error of a literal
        raise ApiError(400, f"{name} is not valid JSON ({exc})", error="invalid_header") from None
