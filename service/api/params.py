"""Unknown query parameters are refused (422 ``unknown_parameter``), not ignored.

A misspelt filter (``?serail=...``) would otherwise answer every result as
if it matched: the client could not tell a wrong name from an empty search.
"""

from __future__ import annotations

from fastapi import Request
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute

from .errors import ApiError


def known_parameters(request: Request) -> None:
    """A router dependency: every query parameter must be one the route declares."""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute):
        return
    declared = _query_names(route.dependant)
    unknown = sorted(set(request.query_params.keys()) - declared)
    if unknown:
        known = ", ".join(sorted(declared)) or "none"
        raise ApiError(
            422,
            "unknown_parameter",
            f"unknown query parameter {', '.join(repr(u[:64]) for u in unknown[:5])}; "
            f"this operation takes: {known}",
        )


def _query_names(dependant: Dependant) -> set[str]:
    """The query parameters of a route and of every dependency it has."""
    names: set[str] = set()
    todo = [dependant]
    while todo:
        d = todo.pop()
        names.update(p.alias for p in d.query_params)
        todo.extend(d.dependencies)
    return names
