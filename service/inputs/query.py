"""Unknown query parameters are refused: ``?output=`` for ``?outputs=`` is a 422 naming the parameters the route
takes, not a request quietly answered with the defaults."""

from __future__ import annotations

from typing import Any

from fastapi import Request

from service.http.errors import ApiError


def known_query_parameters(request: Request) -> list[str]:
    """The query parameters the matched route declares (aliases, e.g. ``input``), sorted."""
    names: set[str] = set()

    def walk(dependant: Any) -> None:  # the route's own parameters and its dependencies'
        names.update(param.alias for param in dependant.query_params)
        for sub in dependant.dependencies:
            walk(sub)

    dependant = getattr(request.scope.get("route"), "dependant", None)
    if dependant is not None:
        walk(dependant)
    return sorted(names)


def reject_unknown_query(request: Request) -> None:
    """A router dependency: ApiError 422 (``invalid_parameters``) for a query parameter the route does not take."""
    known = known_query_parameters(request)
    if unknown := sorted(set(request.query_params) - set(known)):
        takes = f"it takes {', '.join(known)}" if known else "it takes none"
        raise ApiError(422, f"unknown query parameter{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} for "
                            f"{request.method} {request.url.path}: {takes}", error="invalid_parameters")
