"""The numbers of an Open Inference Protocol JSON request read without a Python object per number.

``json.loads`` makes a Python float (24 bytes) and a list slot (8 bytes) of every number: a 60 MiB body of
``"data": [0, 0, ...]`` (21 M numbers) took 1.5 GB and seconds of the event loop. So the numeric lists are cut out
of the body first (each ``"data": [...]`` holding only numbers, brackets, commas and white space), their numbers
are counted before anything is allocated and read by numpy's C text reader; what is left (names, shapes,
datatypes, parameters) is at most :data:`MAX_REST_BYTES` and goes through ``json.loads``, each cut list replaced by
a marker string that names it. A ``data`` that is not a list of JSON numbers (strings such as ``"1"``, ``true``,
``NaN``) is left in the rest and refused by the caller.

:func:`max_json_body` and :func:`max_json_values` bound a whole body by what the model's largest input could need,
so the route refuses (413) before it reads or parses more.
"""

from __future__ import annotations

import json
import re
import uuid
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

MAX_REST_BYTES = 1 << 16  # a JSON request without its numeric lists: names, shapes and parameters
# The longest JSON text one number needs: float64's longest repr ("-2.2250738585072014e-308", 24 characters), a
# comma, a space and a share of the nesting brackets.
MAX_VALUE_CHARS = 32
DATA_LIST = re.compile(rb'"data"\s*:\s*(\[[-+.eE0-9,\[\]\s]*\])')
_BRACKETS_TO_SPACES = bytes.maketrans(b"[]", b"  ")
# the characters of a list of numbers, by class: white space, "[", "]", ",", a number's
_SPACE, _OPEN, _CLOSE, _COMMA, _DIGIT = range(5)
_CLASS = np.zeros(256, np.uint8)
_CLASS[list(b"[],")] = (_OPEN, _CLOSE, _COMMA)
_CLASS[list(b"-+.eE0123456789")] = _DIGIT
_DEPTH_STEP = np.array([0, 1, -1, 0, 0], np.int8)  # by class: "[" opens a list, "]" closes one
# neighbours (white space between them aside) no JSON list of numbers has: "[,", ",,", ",]", "][", "]1", "1["
_MISPLACED = np.zeros((5, 5), bool)
for _first, _second in ((_OPEN, _COMMA), (_COMMA, _COMMA), (_COMMA, _CLOSE), (_CLOSE, _OPEN), (_CLOSE, _DIGIT),
                        (_DIGIT, _OPEN)):
    _MISPLACED[_first, _second] = True
_CHUNK = 1 << 20  # characters checked at once: their temporaries are a few times this
_INTEGER_RANGES = {np.dtype(code): (np.iinfo(code).min, np.iinfo(code).max)
                   for code in ("i1", "<i2", "<i4", "<i8", "u1", "<u2", "<u4", "<u8")}


class JsonTensorError(ValueError):
    """A request's numbers cannot be read: the message says what was expected."""


def max_json_values(largest_input: int) -> int:
    """Commas a JSON body may hold: the largest input's numbers and what the rest of a request could hold."""
    return largest_input + MAX_REST_BYTES


def max_json_body(largest_input: int) -> int:
    """Bytes a JSON body may have: ``largest_input`` numbers of at most :data:`MAX_VALUE_CHARS` each, and the
    rest."""
    return largest_input * MAX_VALUE_CHARS + MAX_REST_BYTES


@dataclass(frozen=True)
class NumericList:
    """One cut ``"data"`` list: its text (numbers, commas, brackets, white space)."""

    text: bytes | memoryview

    def values(self, name: str, dtype: np.dtype, count: int) -> np.ndarray:
        """Its ``count`` numbers as ``dtype`` (flat); JsonTensorError for another count, a number that is not one,
        an integer datatype given a fraction or a number out of its range."""
        text = bytes(self.text)
        commas = text.count(b",")
        found = 0 if commas == 0 and not text.strip(b"[] \t\r\n") else commas + 1
        if found != count:
            raise JsonTensorError(f"input {name!r}: 'data' holds {found} values, expected {count}")
        _check_list(name, text)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy warns (and stops) at text that is not a number
            try:
                numbers = np.fromstring(text.translate(_BRACKETS_TO_SPACES), dtype=np.float64, sep=",")
            except (ValueError, DeprecationWarning) as exc:
                raise JsonTensorError(f"input {name!r}: 'data' holds text that is not a JSON number ({exc})") from None
        del text
        if numbers.size != count:
            raise JsonTensorError(f"input {name!r}: 'data' holds text that is not a JSON number (read {numbers.size} "
                                  f"of {count} values)")
        if dtype in _INTEGER_RANGES:
            low, high = _INTEGER_RANGES[dtype]
            bad = ~((numbers == np.trunc(numbers)) & (numbers >= low) & (numbers <= high))
            if bad.any():
                index = int(np.argmax(bad))
                raise JsonTensorError(f"input {name!r}: 'data' value {float(numbers[index])!r} at {index} is not "
                                      f"{dtype.name}: integers in [{low}, {high}] expected")
        with np.errstate(over="ignore"):  # a float beyond the datatype becomes inf, refused as a value (422)
            return numbers.astype(dtype)


def _check_list(name: str, text: bytes) -> None:
    """JsonTensorError unless ``text`` (numbers, brackets, commas and white space) is one JSON list of numbers and
    lists: no misplaced comma or bracket, no two numbers apart by white space alone, and every bracket but the last
    closes an inner list. numpy over classes of characters, a chunk at a time (no Python object per character)."""
    previous, spaced_end, depth = _SPACE, False, 0
    for start in range(0, len(text), _CHUNK):
        classes = _CLASS[np.frombuffer(text, np.uint8, count=min(_CHUNK, len(text) - start), offset=start)]
        after_space = np.empty(classes.size, bool)
        after_space[0] = spaced_end
        np.equal(classes[:-1], _SPACE, out=after_space[1:])
        tokens = classes != _SPACE
        spaced_end = bool(classes[-1] == _SPACE) or (spaced_end and not tokens.any())
        after_space, classes = after_space[tokens], classes[tokens]
        if not classes.size:
            continue
        firsts = np.concatenate(([previous], classes[:-1]))
        bad = _MISPLACED[firsts, classes] | ((firsts == _DIGIT) & (classes == _DIGIT) & after_space)
        if previous == _SPACE:
            bad[0] = False
        if bad.any():
            raise JsonTensorError(f"input {name!r}: 'data' is not a JSON list of numbers (a misplaced comma, bracket "
                                  f"or space near character {start + int(np.argmax(bad))} of the list)")
        depths = np.cumsum(_DEPTH_STEP[classes], dtype=np.int64) + depth
        if depths.min() < 0 or (start and depth == 0) or (depths[:-1] == 0).any():
            raise JsonTensorError(f"input {name!r}: 'data' is not one JSON list: its brackets do not nest")
        previous, depth = classes[-1], int(depths[-1])
    if depth != 0:
        raise JsonTensorError(f"input {name!r}: 'data' is not one JSON list: its brackets do not nest")


def split_request(body: bytes | bytearray | memoryview) -> tuple[Any, dict[str, NumericList]]:
    """The request's JSON with each numeric ``"data"`` list replaced by a marker string, and marker -> list.
    JsonTensorError when what is left is longer than :data:`MAX_REST_BYTES` or is not JSON."""
    view = memoryview(body)
    marker = f"numbers-{uuid.uuid4().hex}-"  # no client can have written it
    pieces: list[bytes] = []
    lists: dict[str, NumericList] = {}
    start = rest = 0
    for match in DATA_LIST.finditer(body):
        rest += match.start(1) - start
        if rest > MAX_REST_BYTES:
            break
        key = f"{marker}{len(lists)}"
        pieces += [bytes(view[start:match.start(1)]), json.dumps(key).encode()]
        lists[key] = NumericList(view[match.start(1):match.end(1)])
        start = match.end(1)
    rest += len(body) - start
    if rest > MAX_REST_BYTES:
        raise JsonTensorError(f"the JSON request holds {rest} bytes or more besides its lists of numbers, at most "
                              f"{MAX_REST_BYTES} accepted ('data' must be a list of JSON numbers; send large tensors "
                              "as binary tensor data)")
    pieces.append(bytes(view[start:]))
    try:
        parsed = json.loads(b"".join(pieces))
    except (ValueError, RecursionError) as exc:
        raise JsonTensorError(f"the request is not a JSON inference request ({str(exc)[:120]})") from None
    return parsed, lists
