"""uvicorn's HTTP/1.1 protocol (h11) with a deadline for a request's headers and one for its body.

uvicorn times out an idle keep-alive connection (``timeout_keep_alive``, reset by any byte
received) but gives a request no deadline: a client that opens a connection and sends its
request line a byte at a time (slowloris), or its body, holds the connection, its buffers and
a file descriptor for as long as it likes. An ASGI middleware cannot help with the headers: the
app is only called once they are complete. So the deadlines live in the protocol:

* **headers**: from the connection's opening, or the end of its previous response, the next
  request's line and headers must be in within ``header_timeout`` seconds, however the bytes
  trickle in (bytes received do not restart the clock);
* **body**: from the end of the headers, the body must be in within ``body_timeout`` seconds.

A connection past a deadline is answered ``408 request_timeout`` (JSON, ``Connection: close``;
nothing more if a response has started) and closed; an app still waiting for the body is told
the client disconnected. Nothing blocks meanwhile: the event loop serves every other connection
(no thread is held by a connection waiting for bytes).

:class:`TimedH11Protocol` reads the two deadlines from the ``PROBEGRID_*`` settings of the
process (worker processes: :func:`service.main.run` sets them); :func:`timed_protocol` gives a
subclass with the deadlines of a settings object, for a server in this process.
"""

from __future__ import annotations

import asyncio
from typing import Any, Literal

from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_body
from service.settings import Settings, load_settings

__all__ = ["TimedH11Protocol", "timed_protocol"]


def _timeout_response() -> bytes:
    body = error_body("request_timeout",
                      "The request was not received in time; the connection is closed.")
    head = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
            b"connection: close\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n")
    return head + body


class TimedH11Protocol(H11Protocol):
    """:class:`uvicorn.protocols.http.h11_impl.H11Protocol` with the header and body deadlines
    of the module docstring (``header_timeout``, ``body_timeout``: seconds; None: from the
    process's settings)."""

    header_timeout: float | None = None
    body_timeout: float | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        cls = type(self)
        if cls.header_timeout is None or cls.body_timeout is None:
            settings = load_settings()
            cls.header_timeout = settings.header_timeout
            cls.body_timeout = settings.body_timeout
        self._deadline: asyncio.TimerHandle | None = None
        self._waiting: Literal["headers", "body"] | None = None
        self._request: object = None  # the cycle whose headers were seen last

    # the clock
    def _arm(self, what: Literal["headers", "body"]) -> None:
        self._disarm()
        seconds = self.header_timeout if what == "headers" else self.body_timeout
        assert seconds is not None
        self._waiting = what
        self._deadline = self.loop.call_later(seconds, self._expired)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        self._deadline = None
        self._waiting = None

    def _expired(self) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        cycle = self.cycle
        if self._waiting == "headers" or cycle is None or not cycle.response_started:
            self.transport.write(_timeout_response())
        self.logger.info("%s timed out waiting for the request's %s; closed",
                         "%s:%d" % self.client if self.client else "a client", self._waiting)
        self._waiting = None
        self.transport.close()  # connection_lost tells a waiting app the client is gone

    # the protocol's events
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm("headers")

    def handle_events(self) -> None:
        super().handle_events()
        cycle = self.cycle
        if cycle is None or self.transport.is_closing():
            return
        if cycle is not self._request:  # a request's headers are in
            self._request = cycle
            if cycle.more_body:
                self._arm("body")
            else:
                self._disarm()
        elif self._waiting == "body" and not cycle.more_body:
            self._disarm()

    def on_response_complete(self) -> None:
        if not self.transport.is_closing():
            self._arm("headers")  # the next request's (a pipelined one disarms it at once)
        super().on_response_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)


def timed_protocol(settings: Settings) -> type[TimedH11Protocol]:
    """:class:`TimedH11Protocol` with the deadlines of ``settings``."""
    return type("TimedH11Protocol", (TimedH11Protocol,),
                {"header_timeout": settings.header_timeout,
                 "body_timeout": settings.body_timeout})
