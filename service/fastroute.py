"""A route class that resolves a hot endpoint's arguments directly for well-formed requests.

FastAPI resolves an endpoint's arguments per request with its generic dependency solver
(sub-dependencies, one pydantic validation per parameter, error collection). For ``/sh`` and
``/maps`` that machinery costs more than the interpolation itself (about 40-60 us of the
request, measured in-process), which is what the service's load targets are about.

:class:`FastPathRoute` keeps the endpoint a normal FastAPI operation -- its declared parameters
and dependencies still document it in OpenAPI and still validate every request they are asked
to -- and adds a *resolver*, attached with :func:`fast_path`: a plain function from the request
to the endpoint's keyword arguments for the common, well-formed request. It returns None whenever
it is not certain to agree with FastAPI (a parameter missing, non-canonical or percent-encoded, a
value outside the declared range); the request then takes FastAPI's own handler, so every
validation error is FastAPI's, unchanged. A resolver may raise only what the endpoint's own
dependencies raise for that request (:class:`service.errors.ApiError`), by calling the same code.

Requests also take FastAPI's handler while ``app.dependency_overrides`` is not empty or an
OpenTelemetry request span is active (``fastapi.telemetry``), so overrides and traces keep
working. A resolver replaces the whole dependency resolution, so a fast-path route must have no
dependencies besides its parameters: the route refuses ``dependencies=`` (ValueError), and its
router must not be included with ``dependencies=`` either. Either way the endpoint must return a :class:`starlette.responses.Response` (no
``response_model`` serialisation happens on the fast path; FastAPI passes a returned Response
through unchanged as well).
"""

from __future__ import annotations

import inspect
from collections.abc import Awaitable, Callable
from typing import Any, Final, TypeVar

from fastapi import Request, Response
from fastapi.routing import APIRoute
from fastapi.telemetry import get_telemetry_data

__all__ = ["FastPathRoute", "Resolver", "fast_path"]

#: ``resolver(request) -> kwargs or None`` (see the module docstring).
Resolver = Callable[[Request], dict[str, Any] | None]
F = TypeVar("F", bound=Callable[..., Awaitable[Response]])

_ATTRIBUTE: Final = "__probegrid_resolver__"


def fast_path(resolver: Resolver) -> Callable[[F], F]:
    """Decorator attaching ``resolver`` to an async endpoint served by a :class:`FastPathRoute`.

    Apply it below the route decorator (it must run first)::

        @router.get("/sh", ...)
        @fast_path(resolve_sh)
        async def get_sh(request: Request, query: ProbeQueryDep) -> Response: ...
    """

    def mark(endpoint: F) -> F:
        setattr(endpoint, _ATTRIBUTE, resolver)
        return endpoint

    return mark


class FastPathRoute(APIRoute):
    """:class:`fastapi.routing.APIRoute` with a resolver fast path (see the module docstring).

    Use it as an ``APIRouter``'s ``route_class``; endpoints without :func:`fast_path` behave as
    in a plain APIRoute.
    """

    def get_route_handler(self) -> Callable[[Request], Awaitable[Response]]:
        fastapi_handler = super().get_route_handler()
        resolver: Resolver | None = getattr(self.endpoint, _ATTRIBUTE, None)
        if resolver is None:
            return fastapi_handler
        endpoint = self.endpoint
        if not inspect.iscoroutinefunction(endpoint):
            raise ValueError(f"A fast path needs an async endpoint; {endpoint.__name__} is not.")
        if self.dependencies:
            raise ValueError(
                f"The fast path of {endpoint.__name__} would bypass the route's dependencies; "
                "give it none or drop the resolver."
            )

        async def handler(request: Request) -> Response:
            if getattr(request.app, "dependency_overrides", None) or (
                get_telemetry_data() is not None
            ):
                return await fastapi_handler(request)
            kwargs = resolver(request)
            if kwargs is None:
                return await fastapi_handler(request)
            return await endpoint(**kwargs)

        return handler
