"""A cap on request bodies, enforced while the body streams in (HTTP 413).

Checked twice: a declared ``Content-Length`` above the cap is refused before
anything is read, and bodies without one (chunked) are counted as they
arrive, so no upload can fill memory or the temporary directory.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .errors import error_response


class _TooLarge(Exception):
    pass


class BodySizeLimit:
    """ASGI middleware refusing request bodies above ``max_bytes`` with 413."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = int(max_bytes)

    def _refuse(self) -> object:
        mb = self.max_bytes / 1e6
        return error_response(413, "payload_too_large", f"the request body exceeds {mb:g} MB")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = 0
                if declared > self.max_bytes:
                    await self._refuse()(scope, receive, send)  # type: ignore[operator]
                    return
        seen = 0
        exceeded = False
        answered = False

        async def refuse() -> None:
            nonlocal answered
            if not answered:
                answered = True
                await self._refuse()(scope, receive, send)  # type: ignore[operator]

        async def counting_receive() -> Message:
            nonlocal seen, exceeded
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:
                    exceeded = True
                    raise _TooLarge
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal answered
            if exceeded:
                # Whatever the app answers to the aborted body (parsers wrap
                # the error as they like), the client gets the 413.
                await refuse()
                return
            if message["type"] == "http.response.start":
                answered = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except Exception:
            if not exceeded:
                raise
            await refuse()
