"""Methods per path: ``OPTIONS`` and 405 answered with every method the path has.

Starlette dispatches route by route, and each route of FastAPI carries one
method: ``GET /v1/parts`` and ``POST /v1/parts`` are two routes. A method a
path lacks gets the 405 of the first route whose path matched, so ``Allow``
names that route's methods alone, and ``OPTIONS`` (which no route declares)
is a 405 too. RFC 9110 asks otherwise: ``Allow`` lists the methods the
*resource* supports (section 10.2.1), and OPTIONS asks for exactly that
(section 9.3.7). This middleware answers both from the union of the methods
of every route matching the path:

- ``OPTIONS``: 204 No Content with ``Allow`` (a success, as 9.3.7 describes
  it; there is nothing to send but the header);
- a method the path lacks: 405 with the full ``Allow`` and the error body;
- anything else, and paths no route has (404), go on to the router.
"""

from __future__ import annotations

from collections.abc import Sequence

from starlette.responses import Response
from starlette.routing import Match, Route, Router
from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import error_response

_ORDER = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


class MethodRouting:
    """ASGI middleware answering ``OPTIONS`` and unsupported methods per path (see module)."""

    def __init__(self, app: ASGIApp, routers: Sequence[Router]) -> None:
        self.app = app
        self.routers = routers  # read per request: routes added later count too

    def allowed(self, scope: Scope) -> set[str]:
        """Every method of the routes whose path matches ``scope``'s (empty: no such path)."""
        methods: set[str] = set()
        for route in (r for router in self.routers for r in router.routes):
            # An included router appears in its parent as another kind of route: skipped,
            # its own routes are read from it.
            if isinstance(route, Route) and route.methods:
                match, _ = route.matches(scope)
                if match != Match.NONE:
                    methods |= route.methods
        return methods

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        methods = self.allowed(scope)
        method = scope["method"]
        if not methods or method in methods:
            await self.app(scope, receive, send)
            return
        methods.add("OPTIONS")
        allow = ", ".join(
            sorted(methods, key=lambda m: (_ORDER.index(m) if m in _ORDER else 99, m))
        )
        response: Response
        if method == "OPTIONS":
            response = Response(status_code=204, headers={"Allow": allow})
        else:
            response = error_response(
                405,
                "method_not_allowed",
                f"{method} is not a method of this resource; it allows {allow}",
                headers={"Allow": allow},
            )
        await response(scope, receive, send)


def _rank(method: str) -> tuple[int, str]:
    return (_ORDER.index(method) if method in _ORDER else len(_ORDER), method)
