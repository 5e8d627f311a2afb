"""Model registry: ``@register_model("name")`` on a builder, ``create_model("name", **cfg)`` to build.

Builders take keyword-only arguments and raise ``ValueError`` naming a bad value; ``create_model``
passes the config through untouched (it is not mutated). Tiny test variants are registered like the
real ones, so tests build them by name.

The modules that register built-in models are imported lazily on the first lookup (no work at
import time of this module); a package adding models lists its module in ``BUILTIN_MODEL_MODULES``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, TypeVar

from torch import nn

Builder = TypeVar("Builder", bound=Callable[..., nn.Module])

# Modules whose import registers models (each decorates its builders with @register_model).
BUILTIN_MODEL_MODULES: tuple[str, ...] = ("models.detector", "models.segmenter.builders", "models.baselines")

_REGISTRY: dict[str, Callable[..., nn.Module]] = {}
_builtins_loaded = False


class UnknownModelError(KeyError):
    """``create_model`` was asked for a name nobody registered."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


def register_model(name: str) -> Callable[[Builder], Builder]:
    """Decorator registering ``builder`` under ``name``; a name can be registered once only."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"model name must be a non-empty string, got {name!r}")

    def decorator(builder: Builder) -> Builder:
        existing = _REGISTRY.get(name)
        if existing is not None and existing is not builder:
            raise ValueError(
                f"model name {name!r} is already registered to {existing.__module__}.{existing.__qualname__}"
            )
        _REGISTRY[name] = builder
        return builder

    return decorator


def _load_builtins() -> None:
    global _builtins_loaded
    if not _builtins_loaded:
        for module in BUILTIN_MODEL_MODULES:
            importlib.import_module(module)
        _builtins_loaded = True


def list_models() -> list[str]:
    """Sorted names of every registered model."""
    _load_builtins()
    return sorted(_REGISTRY)


def get_builder(name: str) -> Callable[..., nn.Module]:
    """The builder registered under ``name``; :class:`UnknownModelError` names the known ones."""
    _load_builtins()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownModelError(f"unknown model {name!r}: expected one of {sorted(_REGISTRY)}") from None


def create_model(name: str, **cfg: Any) -> nn.Module:
    """Build the model registered under ``name`` with keyword-only config ``cfg``.

    Raises :class:`UnknownModelError` for an unknown name, ``TypeError`` for an argument the builder
    does not take, and ``ValueError`` (from the builder) for a bad value.
    """
    return get_builder(name)(**cfg)
