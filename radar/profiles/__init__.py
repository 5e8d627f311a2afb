"""Radar presets by name (``carrada``, ``nxp``, ``small``: data files in ``radar/profiles/presets/``) and profile
files by path.

:class:`RadarProfile` itself lives in :mod:`radar.profiles.profile` and the file format in
:mod:`radar.profiles.files`; this module looks radars up, so it is the one most code imports.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from radar.profiles.files import ProfileError, load_profile_file, profile_from_dict, profile_to_dict
from radar.profiles.profile import SPEED_OF_LIGHT, ChirpParameters, RadarProfile

__all__ = ["BUILTIN_PRESETS", "SPEED_OF_LIGHT", "ChirpParameters", "RadarProfile", "UnknownPresetError",
           "describe_for_storage", "get_profile", "resolve_profile"]

BUILTIN_PRESETS = ("carrada", "nxp", "small")  # data files in radar/profiles/presets/


@functools.cache
def _builtin(name: str) -> RadarProfile:
    return load_profile_file(Path(__file__).with_name("presets") / f"{name}.toml")


def __getattr__(attr: str):
    """``CARRADA``, ``NXP``, ``SMALL`` and ``PRESETS`` load from their files on first use."""
    if attr in ("CARRADA", "NXP", "SMALL"):
        return _builtin(attr.lower())
    if attr == "PRESETS":
        return {name: _builtin(name) for name in BUILTIN_PRESETS}
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")


class UnknownPresetError(KeyError):
    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


def get_profile(name: str | Path | RadarProfile) -> RadarProfile:
    """A built-in profile by name (``carrada``, ``nxp``, ``small``), or a profile file (``.toml`` or
    ``.json`` path: a radar is a file, not a code change); profiles pass through."""
    if isinstance(name, RadarProfile):
        return name
    if isinstance(name, str) and name in BUILTIN_PRESETS:
        return _builtin(name)
    if isinstance(name, Path) or (isinstance(name, str) and name.endswith((".toml", ".json"))):
        return load_profile_file(name)
    raise UnknownPresetError(
        f"unknown radar preset {name!r}: expected one of {sorted(BUILTIN_PRESETS)} or a .toml/.json profile file"
    )


def resolve_profile(name: str, description: dict[str, Any] | None = None, *, source: str = "profile") -> RadarProfile:
    """The radar a store, recording or checkpoint names: a built-in preset by its name (the preset's file as it is
    today, whatever description an older store kept), else the radar its stored file-form ``description``
    (:func:`describe_for_storage`) defines."""
    if name in BUILTIN_PRESETS:
        return get_profile(name)
    if description is not None:
        return profile_from_dict(description, source=source)
    raise ProfileError(f"{source}: radar {name!r} is not a built-in preset and no profile description is stored")


def describe_for_storage(profile: RadarProfile) -> dict[str, Any] | None:
    """The file form of a radar that is not a built-in preset (what stores, checkpoints and ONNX manifests keep so
    that it travels with them, read back by :func:`resolve_profile`); None for a built-in preset, which its
    name identifies."""
    if profile.name in BUILTIN_PRESETS and profile == get_profile(profile.name):
        return None
    return profile_to_dict(profile)
