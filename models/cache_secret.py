"""This user's secret that seals what the caches keep (the ONNX exports, the int8 calibrations): whoever can write to
a cache folder can neither predict an entry's name nor seal an entry of their own, because the secret lives outside
every cache."""

from __future__ import annotations

import os
from pathlib import Path

from models.environment import environment


def cache_secret() -> bytes:
    """``$RADARSEG_ONNX_CACHE_KEY_FILE``, else ``~/.config/radarseg/onnx-cache.key`` (32 random bytes, made on first
    use, readable by the user only)."""
    path = environment().onnx_cache_key_file or Path.home() / ".config" / "radarseg" / "onnx-cache.key"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another process made it first
            return path.read_bytes()
        with os.fdopen(fd, "wb") as out:
            out.write(os.urandom(32))
    return path.read_bytes()
