"""Error responses: every failure is a JSON :class:`service.schemas.ErrorOut`; a client's mistake is a 4xx.

===========================================  ======  ======================
cause                                        status  ``error``
===========================================  ======  ======================
unknown route, grid or map kind              404     ``not_found``
method not allowed on a route                405     ``method_not_allowed``
malformed JSON body                          400     ``malformed_json``
missing / non-finite / out-of-range values   422     ``invalid_request``
a value the library rejects (ValueError)     422     ``invalid_request``
body over ``max_body_bytes``, batch too big  413     ``too_large``
estimated cost over ``request_budget``       422     ``over_budget``
headers or body not in within their timeout  408     ``request_timeout``
store files unreadable (server side)         503     ``store_unavailable``
scratch space full or failing (server side)  503     ``scratch_unavailable``
all heavy-request slots taken (lights/shade)  503     ``busy``
anything else (a server bug)                 500     ``internal_error``
===========================================  ======  ======================

The last row is a last resort: :class:`LastResortMiddleware` logs the exception with its traceback
and a reference that the response carries, and answers ``500 internal_error`` with a JSON body: a
bug of the server is a server error, never blamed on the request, and never takes the server down.
Tests fuzz the API and check that it never fires.

:class:`BodyLimitMiddleware` refuses bodies over the limit before the app reads them: a declared
``Content-Length`` over the limit is answered at once; otherwise the body is read up to the limit
and replayed to the app.
"""

from __future__ import annotations

import json
import logging
import secrets
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from probegrid.errors import StoreError

__all__ = [
    "ApiError",
    "BodyLimitMiddleware",
    "LastResortMiddleware",
    "error_body",
    "install_error_handlers",
]

log = logging.getLogger("probegrid.service")

_CODES = {
    400: "bad_request",
    404: "not_found",
    408: "request_timeout",
    405: "method_not_allowed",
    413: "too_large",
    415: "unsupported_media_type",
    422: "invalid_request",
    500: "internal_error",
    503: "store_unavailable",
}


class ApiError(Exception):
    """An error a route raises on purpose: status, code and one-sentence message."""

    def __init__(self, status: int, message: str, *, code: str | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code or _CODES.get(status, "bad_request")
        self.message = message
        self.headers = headers


def error_body(code: str, message: str, detail: list[dict[str, Any]] | None = None) -> bytes:
    """JSON bytes of an :class:`service.schemas.ErrorOut`."""
    doc: dict[str, Any] = {"error": code, "message": message}
    if detail is not None:
        doc["detail"] = detail
    return json.dumps(doc, separators=(",", ":"), default=str).encode()


def _json(status: int, code: str, message: str, detail: list[dict[str, Any]] | None = None,
          headers: dict[str, str] | None = None) -> Response:
    return Response(error_body(code, message, detail), status_code=status,
                    media_type="application/json", headers=headers)


def _sentence(text: str) -> str:
    text = " ".join(str(text).split()).removeprefix("Value error, ")
    return text if text.endswith(".") else text + "."


def _location(loc: tuple[Any, ...]) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("query", "path", "body", "header"):
        where, rest = parts[0], parts[1:]
        return f"{where} {'.'.join(rest)}" if rest else where
    return ".".join(parts)


def _validation(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, RequestValidationError)
    errors = list(exc.errors())
    detail = [
        {"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")),
         "type": str(e.get("type", ""))}
        for e in errors
    ]
    if any(e.get("type") == "json_invalid" for e in errors):
        return _json(400, "malformed_json", "The request body is not valid JSON.", detail)
    first = errors[0] if errors else {}
    where = _location(tuple(first.get("loc", ())))
    more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
    msg = _sentence(f"{where}: {first.get('msg', 'invalid value')}{more}")
    return _json(422, "invalid_request", msg, detail)


def _http(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    status = exc.status_code if 400 <= exc.status_code < 600 else 500
    code = _CODES.get(status, "bad_request")
    if status == 404 and exc.detail == "Not Found":
        message = f"There is no route {request.url.path}; see /docs for the API."
    elif status == 405:
        message = f"{request.method} is not allowed on {request.url.path}."
    else:
        message = _sentence(str(exc.detail))
    return _json(status, code, message, headers=getattr(exc, "headers", None))


def _api(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, ApiError)
    return _json(exc.status, exc.code, _sentence(exc.message), headers=exc.headers)


def _value(request: Request, exc: Exception) -> Response:
    return _json(422, "invalid_request", _sentence(str(exc)))


def _store(request: Request, exc: Exception) -> Response:
    log.error("store failure on %s %s: %s", request.method, request.url.path, exc)
    return _json(503, "store_unavailable", "The grid's store cannot be read right now.",
                 headers={"Retry-After": "1"})


def install_error_handlers(app: FastAPI) -> None:
    """Register the JSON error handlers of the table in the module docstring."""
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(ApiError, _api)
    app.add_exception_handler(ValueError, _value)
    app.add_exception_handler(StoreError, _store)


async def _send_json(send: Send, status: int, body: bytes,
                     extra: list[tuple[bytes, bytes]] | None = None) -> None:
    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode())] + (extra or [])
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


class LastResortMiddleware:
    """Turn an exception no handler took into a logged ``500 internal_error`` JSON response."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracking_send)
        except Exception:
            ref = secrets.token_hex(6)
            log.exception("internal_error %s: unhandled error on %s %s", ref,
                          scope.get("method"), scope.get("path"))
            if not started:
                msg = (f"The server could not process this request (reference {ref}); "
                       "the cause was logged.")
                await _send_json(send, 500, error_body("internal_error", msg))


class BodyLimitMiddleware:
    """Answer ``413 too_large`` for request bodies over ``max_bytes`` (see module docstring)."""

    def __init__(self, app: ASGIApp, *, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def _too_large(self, send: Send) -> None:
        msg = f"The request body is over the limit of {self.max_bytes} bytes."
        await _send_json(send, 413, error_body("too_large", msg), [(b"connection", b"close")])

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("method") in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.max_bytes:
                    await self._too_large(send)
                    return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                await self._too_large(send)
                return
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
