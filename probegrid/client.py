"""Python client of the probegrid map service (``probegrid serve``), on httpx.

:class:`ProbeGridClient` (blocking) and :class:`AsyncProbeGridClient` (``async``) have the same
methods and options; both build requests and decode responses through one shared base, and differ
only in how they send. Results are the library's types: numpy arrays,
:class:`probegrid.core.cubemap.CubeMap` and :class:`probegrid.store.StoreManifest`.

>>> with ProbeGridClient("http://127.0.0.1:8000") as pg:          # doctest: +SKIP
...     sample = pg.sh_at("sample", (1.0, 1.5, 0.5))
...     diffuse = pg.maps_at("sample", (1.0, 1.5, 0.5), kind="diffuse")

Maps travel as float32 ``.npy`` (bit-exact); SH and shading results as JSON numbers (exact
round trip of float64).

Options (keyword-only)
----------------------
``timeout``
    Seconds (or an ``httpx.Timeout``) for each network operation -- connecting, and each read
    or write -- not a deadline for the whole call: a server that trickles bytes can take longer,
    and the retries multiply it. Default 10.
``retries``
    Extra attempts after a connection failure or a ``503`` answer, with exponential back-off
    ``backoff * 2^attempt`` seconds (defaults 2 and 0.1). Other errors are never retried.
``transport``
    An httpx transport (e.g. ``httpx.ASGITransport(app)`` to talk to an app in-process).

Exceptions
----------
::

    ProbegridError                 probegrid.errors: the library's one error tree (diagram there)
    +-- ProbeGridError             base of everything this module raises
        +-- InvalidArgumentError       a bad argument, refused before any request (a ValueError)
        +-- ProbeGridConnectionError   the server could not be reached (after the retries)
        +-- ProbeGridTimeoutError      the server did not answer in time
        +-- ProbeGridResponseError     a success status with a body that is not the API's
        +-- ProbeGridHTTPError         the server answered with an error status
            +-- BadRequestError        400, 413, 422: the request was rejected (bad input, limits)
            +-- NotFoundError          404: unknown grid, map kind or route
            +-- ServerError            5xx: a server bug (500) or a store unavailable (503,
                                       after the retries)

An HTTP error carries the server's ``status``, ``code`` (e.g. ``"invalid_request"``) and
``message`` (one sentence), and its ``str()`` is that message.
"""

from __future__ import annotations

import asyncio
import io
import json
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal, Self
from urllib.parse import quote

import httpx
import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import MapKind, MapMethod, SHKind, SHSource, TraceQuality, choices
from probegrid.core.cubemap import CubeMap
from probegrid.core.lights import DirectionalLight, Light, PointLight, SpotLight
from probegrid.errors import ProbegridError
from probegrid.store.manifest import StoreManifest

__all__ = [
    "AsyncProbeGridClient",
    "BadRequestError",
    "GridInfo",
    "InvalidArgumentError",
    "MapSample",
    "NotFoundError",
    "ProbeGridClient",
    "ProbeGridConnectionError",
    "ProbeGridError",
    "ProbeGridHTTPError",
    "ProbeGridResponseError",
    "ProbeGridTimeoutError",
    "SHSample",
    "ServerError",
]



# ------------------------------------------------------------------------------ exceptions
class ProbeGridError(ProbegridError):
    """Base class of the client's errors (under the library's :class:`ProbegridError`)."""


class InvalidArgumentError(ProbeGridError, ValueError):
    """An argument of the call is invalid (checked before any request is sent)."""


class ProbeGridResponseError(ProbeGridError):
    """The server answered with a success status but a body that is not what the API returns
    (the URL may not be a probegrid service)."""


class ProbeGridConnectionError(ProbeGridError):
    """The server could not be reached."""


class ProbeGridTimeoutError(ProbeGridError):
    """The server did not answer in time."""


class ProbeGridHTTPError(ProbeGridError):
    """The server answered with an error status.

    Attributes
    ----------
    status : int
    code : str
        The server's error code (``"not_found"``, ``"invalid_request"``, ...).
    message : str
        The server's one-sentence explanation.
    method, url : str
        The request that failed.
    """

    def __init__(self, status: int, code: str, message: str, *, method: str, url: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.method = method
        self.url = url


class BadRequestError(ProbeGridHTTPError):
    """400, 413 or 422: the server rejected the request."""


class NotFoundError(ProbeGridHTTPError):
    """404: no such grid, map kind or route."""


class ServerError(ProbeGridHTTPError):
    """5xx."""


def _http_error(response: httpx.Response) -> ProbeGridHTTPError:
    status = response.status_code
    try:
        doc = response.json()
        code, message = str(doc["error"]), str(doc["message"])
    except (ValueError, KeyError, TypeError):
        code, message = f"http_{status}", response.text[:200] or response.reason_phrase
    cls = (
        NotFoundError if status == 404
        else ServerError if status >= 500
        else BadRequestError
    )
    return cls(status, code, message, method=response.request.method, url=str(response.request.url))


# ------------------------------------------------------------------------------ results
@dataclass(frozen=True)
class GridInfo:
    """A served grid (``GET /v1/grids``); ``manifest`` only from :meth:`ProbeGridClient.grid`.

    Attributes
    ----------
    name : str
    counts : (3,) int
    bounds_min, bounds_max, spacing : (3,) float
    probes, valid_probes : int
    kinds : tuple of str
    map_sizes : dict of str -> tuple of int
        Face size of each level per kind.
    specular_levels : int
    visibility : bool
        Distance moments stored (visibility-aware weights with a normal).
    scene_hash, created : str
    manifest : StoreManifest or None
    """

    name: str
    counts: tuple[int, int, int]
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    spacing: tuple[float, float, float]
    probes: int
    valid_probes: int
    kinds: tuple[str, ...]
    map_sizes: dict[str, tuple[int, ...]]
    specular_levels: int
    visibility: bool
    scene_hash: str
    created: str
    manifest: StoreManifest | None = None

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> GridInfo:
        manifest = doc.get("manifest")
        return cls(
            name=doc["name"],
            counts=tuple(doc["counts"]),  # type: ignore[arg-type]
            bounds_min=tuple(doc["bounds_min"]),  # type: ignore[arg-type]
            bounds_max=tuple(doc["bounds_max"]),  # type: ignore[arg-type]
            spacing=tuple(doc["spacing"]),  # type: ignore[arg-type]
            probes=int(doc["probes"]),
            valid_probes=int(doc["valid_probes"]),
            kinds=tuple(doc["kinds"]),
            map_sizes={k: tuple(v) for k, v in doc["map_sizes"].items()},
            specular_levels=int(doc["specular_levels"]),
            visibility=bool(doc["visibility"]),
            scene_hash=doc["scene_hash"],
            created=doc["created"],
            manifest=None if manifest is None else StoreManifest.model_validate(manifest),
        )


@dataclass(frozen=True, eq=False)
class SHSample:
    """SH radiance at a position (``GET /v1/grids/{grid}/sh``).

    Attributes
    ----------
    coefficients : (9, 3) float64
        RGB radiance coefficients ``L_lm``, index ``l(l+1)+m``.
    probes : (k,) int64
        Linear indices of the probes blended (non-zero weight).
    weights : (k,) float64
        Their weights (sum 1, unless ``unlit``).
    sampled_position : (3,) float64
        Where the probes were blended: the position, clamped onto the grid box grown by a
        quarter cell (linear extrapolation up to there).
    outside, unlit, visibility : bool
        Flags of the query (see the service; ``visibility``: a normal was given).
    visibility_test : str
        The visibility test the weights went through: ``"segments"`` (exact, against the
        scene's triangles: a probe behind a wall has no weight), ``"moments"`` (DDGI's
        Chebyshev test, a store without triangles and a normal) or ``"none"``.
    sh : str
        Which coefficients: ``"deringed"`` (each probe's irradiance non-negative everywhere,
        the default) or ``"raw"``.
    sh_source : str
        ``"store"``, or ``"computed"`` when the server deringed an older store's SH itself.
    source : str
        What was interpolated: ``"field"``, the store's SH field (then ``probes`` are indices
        of its lattice), or ``"probes"``.
    """

    coefficients: NDArray[np.float64]
    probes: NDArray[np.int64]
    weights: NDArray[np.float64]
    sampled_position: NDArray[np.float64]
    outside: bool
    unlit: bool
    visibility: bool
    visibility_test: str = "none"
    sh: str = "raw"
    sh_source: str = "store"
    source: str = "probes"


@dataclass(frozen=True, eq=False)
class MapSample:
    """One level of a blended cube map and how it was blended (:meth:`ProbeGridClient.map_at`).

    Attributes
    ----------
    faces : (6, n, n, 3) float32
    kind : str
    level : int
    probes : (k,) int64
    weights : (k,) float64
        The probes blended and their weights (the ``X-Probegrid-Probes`` header).
    outside, unlit : bool
    visibility_test : str
        ``"segments"``, ``"moments"`` or ``"none"`` (see :class:`SHSample`).
    method : str
        How the map was made: ``"trace"`` (a probe traced at the point) or ``"blend"`` (the
        ``X-Probegrid-Method`` header).
    """

    faces: NDArray[np.float32]
    kind: str
    level: int
    probes: NDArray[np.int64]
    weights: NDArray[np.float64]
    outside: bool
    unlit: bool
    visibility_test: str
    method: str = "blend"


# ------------------------------------------------------------------------------ request building
def _vec3(value: ArrayLike, name: str) -> list[float]:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"{name} must be three finite numbers, got {value!r}.") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InvalidArgumentError(f"{name} must be three finite numbers, got {value!r}.")
    return a.tolist()


def _rows(value: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"{name} must be numbers of shape (n, 3).") from None
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise InvalidArgumentError(f"{name} must have shape (n, 3) with n >= 1, got "
                                   f"{np.shape(value)}.")
    if not np.all(np.isfinite(a)):
        raise InvalidArgumentError(f"{name} must be finite (no nan or inf components).")
    return a


def _light_json(light: Light) -> dict[str, Any]:
    if isinstance(light, PointLight):
        return {"type": "point", "position": list(light.position), "color": list(light.color),
                "intensity": light.intensity, "range": light.range}
    if isinstance(light, SpotLight):
        return {"type": "spot", "position": list(light.position),
                "direction": list(light.direction), "color": list(light.color),
                "intensity": light.intensity, "range": light.range,
                "inner_cone_angle": light.inner_cone_angle,
                "outer_cone_angle": light.outer_cone_angle}
    if isinstance(light, DirectionalLight):
        return {"type": "directional", "direction": list(light.direction),
                "color": list(light.color), "intensity": light.intensity}
    raise TypeError(f"lights must be PointLight, SpotLight or DirectionalLight, got {light!r}.")


def _per_point(value: ArrayLike, n: int, name: str, components: int) -> NDArray[np.float64]:
    """A material input as one value (``(components,)`` or scalar) or one per point, finite."""
    a = np.asarray(value, dtype=np.float64)
    single = (components,) if components > 1 else ()
    if a.shape not in (single, (n, *single)):
        raise InvalidArgumentError(f"{name} must have shape {single or 'scalar'} or {(n, *single)}, "
                         f"got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise InvalidArgumentError(f"{name} must be finite.")
    return a


@dataclass(frozen=True)
class _Call:
    """One HTTP request to make: method, path, query parameters, JSON body."""

    method: str
    path: str
    params: dict[str, Any] | None = None
    body: Any = None


def _position_params(position: ArrayLike, normal: ArrayLike | None) -> dict[str, Any]:
    x, y, z = _vec3(position, "position")
    params: dict[str, Any] = {"x": repr(x), "y": repr(y), "z": repr(z)}
    if normal is not None:
        nx, ny, nz = _vec3(normal, "normal")
        params.update(nx=repr(nx), ny=repr(ny), nz=repr(nz))
    return params


@contextmanager
def _decoding(response: httpx.Response) -> Iterator[None]:
    """Turn a body that does not decode as the API's answer into ProbeGridResponseError."""
    try:
        yield
    except (ValueError, KeyError, TypeError, IndexError, EOFError) as exc:
        raise ProbeGridResponseError(
            f"{response.request.method} {response.request.url} answered "
            f"{response.status_code} with a body that is not the probegrid API's "
            f"({type(exc).__name__}: {exc}); is this a probegrid service?") from None


def _load_npy(response: httpx.Response) -> NDArray[np.float32]:
    with _decoding(response):
        return np.load(io.BytesIO(response.content), allow_pickle=False)


class _BaseClient:
    """Options, request building and response decoding shared by both clients."""

    def __init__(
        self,
        base_url: str,
        *,
        timeout: float | httpx.Timeout = 10.0,
        retries: int = 2,
        backoff: float = 0.1,
        headers: dict[str, str] | None = None,
    ) -> None:
        if not isinstance(retries, int) or retries < 0:
            raise InvalidArgumentError(f"retries must be an integer >= 0, got {retries!r}.")
        if not (isinstance(backoff, (int, float)) and backoff >= 0):
            raise InvalidArgumentError(f"backoff must be a number >= 0, got {backoff!r}.")
        try:
            url = httpx.URL(str(base_url).rstrip("/"))
        except httpx.InvalidURL as exc:
            raise InvalidArgumentError(f"base_url {base_url!r} is not a valid URL: {exc}.") from None
        if url.scheme not in ("http", "https") or not url.host:
            raise InvalidArgumentError(f"base_url must be an http:// or https:// URL with a host, "
                                       f"got {base_url!r}.")
        self.base_url = str(url)
        self.retries = retries
        self.backoff = float(backoff)
        self._timeout = timeout if isinstance(timeout, httpx.Timeout) else httpx.Timeout(timeout)
        self._headers = {"Accept": "application/json, application/x-npy", **(headers or {})}
        self._levels: dict[tuple[str, str], int] = {}

    # -- retry policy ------------------------------------------------------------------------
    def _delays(self) -> Iterator[float]:
        """Sleep before each attempt: 0, then the back-off sequence."""
        yield 0.0
        for attempt in range(self.retries):
            yield self.backoff * 2**attempt

    @staticmethod
    def _retryable(response: httpx.Response) -> bool:
        return response.status_code == 503

    @staticmethod
    def _transport_error(exc: httpx.TransportError, call: _Call) -> ProbeGridError:
        what = f"{call.method} {call.path}"
        if isinstance(exc, httpx.TimeoutException):
            return ProbeGridTimeoutError(f"{what}: the server did not answer in time ({exc}).")
        return ProbeGridConnectionError(f"{what}: cannot reach the server ({exc}).")

    @classmethod
    def _transport_failure(cls, exc: httpx.TransportError, call: _Call) -> ProbeGridError:
        """The error of an attempt that raised ``exc`` (call it in the ``except`` block).

        Returned when the attempt may be retried (the connection could not be made), raised
        otherwise.
        """
        failure = cls._transport_error(exc, call)
        if isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout)):
            return failure
        raise failure from exc

    @classmethod
    def _response_failure(cls, response: httpx.Response) -> ProbeGridHTTPError | None:
        """None for a success; the error of an answer that may be retried; raises the others."""
        if response.status_code < 400:
            return None
        failure = _http_error(response)
        if not cls._retryable(response):
            raise failure
        return failure

    # -- calls and decoders --------------------------------------------------------------------
    @staticmethod
    def _grids_call() -> _Call:
        return _Call("GET", "/v1/grids")

    @staticmethod
    def _grids_result(r: httpx.Response) -> list[GridInfo]:
        with _decoding(r):
            return [GridInfo.from_json(g) for g in r.json()["grids"]]

    @staticmethod
    def _grid_call(grid: str) -> _Call:
        return _Call("GET", f"/v1/grids/{_segment(grid)}")

    def _grid_result(self, r: httpx.Response) -> GridInfo:
        with _decoding(r):
            info = GridInfo.from_json(r.json())
        for kind in info.kinds:
            self._levels[(info.name, kind)] = len(info.map_sizes[kind])
        return info

    @staticmethod
    def _sh_call(grid: str, position: ArrayLike, normal: ArrayLike | None,
                 sh: str = "deringed", source: str = "field") -> _Call:
        if sh not in _SH_KINDS:
            raise InvalidArgumentError(f"sh must be one of {', '.join(_SH_KINDS)}, got {sh!r}.")
        if source not in _SH_SOURCES:
            raise InvalidArgumentError(
                f"source must be one of {', '.join(_SH_SOURCES)}, got {source!r}.")
        params = _position_params(position, normal)
        if sh != "deringed":
            params["sh"] = sh
        if source != "field":
            params["source"] = source
        return _Call("GET", f"/v1/grids/{_segment(grid)}/sh", params)

    @staticmethod
    def _sh_result(r: httpx.Response) -> SHSample:
        with _decoding(r):
            return _BaseClient._sh_sample(r.json())

    @staticmethod
    def _sh_sample(doc: dict[str, Any]) -> SHSample:
        probes = doc["probes"]
        return SHSample(
            coefficients=np.asarray(doc["coefficients"], dtype=np.float64),
            probes=np.asarray([p["index"] for p in probes], dtype=np.int64),
            weights=np.asarray([p["weight"] for p in probes], dtype=np.float64),
            sampled_position=np.asarray(doc["sampled_position"], dtype=np.float64),
            outside=bool(doc["flags"]["outside"]),
            unlit=bool(doc["flags"]["unlit"]),
            visibility=bool(doc["flags"]["visibility"]),
            # (older servers answer without these: no visibility test, raw SH)
            visibility_test=str(doc["flags"].get("visibility_test", "none")),
            sh=str(doc.get("sh", "raw")),
            sh_source=str(doc.get("sh_source", "store")),
            source=str(doc.get("source", "probes")),
        )

    @staticmethod
    def _map_sample(r: httpx.Response, kind: str, level: int) -> MapSample:
        faces = _load_npy(r)
        with _decoding(r):
            pairs = [p.split(":") for p in r.headers.get("x-probegrid-probes", "").split(",")
                     if p]
            return MapSample(
                faces=faces, kind=kind, level=level,
                probes=np.asarray([int(i) for i, _ in pairs], dtype=np.int64),
                weights=np.asarray([float(w) for _, w in pairs], dtype=np.float64),
                outside=r.headers.get("x-probegrid-outside") == "true",
                unlit=r.headers.get("x-probegrid-unlit") == "true",
                visibility_test=r.headers.get("x-probegrid-visibility", "none"),
                method=r.headers.get("x-probegrid-method", "blend"),
            )

    @staticmethod
    def _map_call(grid: str, position: ArrayLike, normal: ArrayLike | None, kind: str,
                  level: int, method: MapMethod = "trace",
                  quality: TraceQuality = "accurate") -> _Call:
        if method not in _MAP_METHODS:
            raise InvalidArgumentError(
                f"method must be one of {', '.join(_MAP_METHODS)}, got {method!r}.")
        if quality not in _QUALITIES:
            raise InvalidArgumentError(
                f"quality must be one of {', '.join(_QUALITIES)}, got {quality!r}.")
        params = _position_params(position, normal)
        params.update(level=int(level), format="npy", layout="faces", method=method)
        if quality != "accurate":  # (the service's default)
            params["quality"] = quality
        return _Call("GET", f"/v1/grids/{_segment(grid)}/maps/{_segment(kind)}", params)

    @staticmethod
    def _shade_calls(
        grid: str, points: ArrayLike, normals: ArrayLike, views: ArrayLike, *,
        albedo: ArrayLike, f0: ArrayLike, roughness: ArrayLike, batch_size: int,
    ) -> list[_Call]:
        p, n, v = _rows(points, "points"), _rows(normals, "normals"), _rows(views, "views")
        if not p.shape[0] == n.shape[0] == v.shape[0]:
            raise InvalidArgumentError("points, normals and views must have the same number of rows.")
        if not isinstance(batch_size, int) or batch_size < 1:
            raise InvalidArgumentError(f"batch_size must be a positive integer, got {batch_size!r}.")
        total = p.shape[0]
        alb = _per_point(albedo, total, "albedo", 3)
        spec = _per_point(f0, total, "f0", 3)
        rough = _per_point(roughness, total, "roughness", 1)
        calls = []
        for i in range(0, total, batch_size):
            j = min(i + batch_size, total)
            points_json = []
            for k in range(i, j):
                point: dict[str, Any] = {
                    "position": p[k].tolist(), "normal": n[k].tolist(), "view": v[k].tolist()
                }
                if alb.ndim == 2 or spec.ndim == 2 or rough.ndim == 1:
                    point["material"] = {
                        "albedo": (alb[k] if alb.ndim == 2 else alb).tolist(),
                        "f0": (spec[k] if spec.ndim == 2 else spec).tolist(),
                        "roughness": float(rough[k] if rough.ndim == 1 else rough),
                    }
                points_json.append(point)
            material = {"albedo": alb.tolist(), "f0": spec.tolist(), "roughness": float(rough)} \
                if alb.ndim == 1 and spec.ndim == 1 and rough.ndim == 0 else None
            body: dict[str, Any] = {"points": points_json}
            if material is not None:
                body["material"] = material
            calls.append(_Call("POST", f"/v1/grids/{_segment(grid)}/shade", body=body))
        return calls

    @staticmethod
    def _shade_result(r: httpx.Response) -> NDArray[np.float32]:
        with _decoding(r):
            return np.asarray(r.json()["rgb"], dtype=np.float32).reshape(-1, 3)

    @staticmethod
    def _light_call(
        position: ArrayLike, lights: Sequence[Light], *, kind: str, level: int,
        grid: str | None, diffuse_size: int, specular_size: int, specular_levels: int | None,
        normal: ArrayLike | None = None,
    ) -> _Call:
        if not lights:
            raise InvalidArgumentError("light_maps needs at least one light.")
        body = {
            "position": _vec3(position, "position"),
            "normal": None if normal is None else _vec3(normal, "normal"),
            "lights": [_light_json(light) for light in lights],
            "kind": kind, "level": int(level), "grid": grid,
            "diffuse_size": int(diffuse_size), "specular_size": int(specular_size),
            "specular_levels": specular_levels, "format": "npy", "layout": "faces",
        }
        return _Call("POST", "/v1/lights/maps", body=body)

    def _levels_wanted(self, grid: str, kind: str, level: int | None) -> list[int] | None:
        """Levels to fetch for ``maps_at``; None if the grid's level count is not known yet."""
        if level is not None:
            return [int(level)]
        known = self._levels.get((grid, kind))
        return None if known is None else list(range(known))

    def _request_kwargs(self, call: _Call) -> dict[str, Any]:
        kw: dict[str, Any] = {"params": call.params}
        if call.body is not None:
            kw["content"] = json.dumps(call.body, allow_nan=False).encode()
            kw["headers"] = {"Content-Type": "application/json"}
        return kw


#: The ``sh`` choices of :meth:`ProbeGridClient.sh_at` (the service's ``/sh?sh=``).
_SH_KINDS = choices(SHKind)
_SH_SOURCES = choices(SHSource)
#: The ``method`` choices of :meth:`ProbeGridClient.map_at` (the service's ``/maps?method=``).
_MAP_METHODS = choices(MapMethod)
_QUALITIES = choices(TraceQuality)


def _segment(name: str) -> str:
    """A path segment for a grid or kind name (percent-encoded; never a path of its own)."""
    if not isinstance(name, str) or not name:
        raise InvalidArgumentError(f"names must be non-empty strings, got {name!r}.")
    return quote(name, safe="")


# ------------------------------------------------------------------------------ blocking client
class ProbeGridClient(_BaseClient):
    """Blocking client of the map service (see the module docstring for options and errors).

    Parameters
    ----------
    base_url : str
        e.g. ``"http://127.0.0.1:8000"``.
    timeout, retries, backoff, headers, transport
        Keyword-only options (module docstring).
    """

    def __init__(
        self,
        base_url: str,
        *,
        timeout: float | httpx.Timeout = 10.0,
        retries: int = 2,
        backoff: float = 0.1,
        headers: dict[str, str] | None = None,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, timeout=timeout, retries=retries, backoff=backoff,
                         headers=headers)
        self._http = httpx.Client(base_url=self.base_url, timeout=self._timeout,
                                  headers=self._headers, transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, call: _Call) -> httpx.Response:
        failure: ProbeGridError | None = None
        for delay in self._delays():
            if delay:
                time.sleep(delay)
            try:
                response = self._http.request(call.method, call.path,
                                              **self._request_kwargs(call))
            except httpx.TransportError as exc:
                failure = self._transport_failure(exc, call)
                continue
            failure = self._response_failure(response)
            if failure is None:
                return response
        assert failure is not None
        raise failure

    def healthz(self) -> bool:
        """True when the server answers its health check."""
        r = self._send(_Call("GET", "/healthz"))
        with _decoding(r):
            return r.json().get("status") == "ok"

    def grids(self) -> list[GridInfo]:
        """Every served grid."""
        return self._grids_result(self._send(self._grids_call()))

    def grid(self, name: str) -> GridInfo:
        """One grid, with its manifest."""
        return self._grid_result(self._send(self._grid_call(name)))

    def sh_at(self, grid: str, position: ArrayLike, *, normal: ArrayLike | None = None,
              sh: Literal["deringed", "raw"] = "deringed",
              source: Literal["field", "probes"] = "field") -> SHSample:
        """SH radiance coefficients at a position (visibility-aware with a normal), from the
        store's SH field where it has one (``source="probes"``: the probes' blend): deringed
        (irradiance non-negative everywhere) or ``sh="raw"``; the result's ``sh``, ``source``
        and ``visibility_test`` say which SH, what was interpolated and which visibility
        test."""
        return self._sh_result(self._send(self._sh_call(grid, position, normal, sh, source)))

    def map_at(self, grid: str, position: ArrayLike, *, kind: MapKind = "diffuse",
               level: int = 0, normal: ArrayLike | None = None,
               method: MapMethod = "trace", quality: TraceQuality = "accurate") -> MapSample:
        """One level of the map at a position -- traced there (``method="trace"``, the
        default: what a probe baked at the point holds; ``quality`` the trace's preset:
        ``"accurate"``, ``"fast"`` or ``"reference"``, see the service's ``/maps``) or blended
        from the probes (``"blend"``) -- with the probes, weights, flags and visibility test of
        the blend and the method used (:meth:`maps_at` gives the maps alone)."""
        r = self._send(self._map_call(grid, position, normal, kind, level, method, quality))
        return self._map_sample(r, kind, int(level))

    def maps_at(self, grid: str, position: ArrayLike, *, kind: MapKind = "diffuse",
                level: int | None = None, normal: ArrayLike | None = None,
                method: MapMethod = "trace", quality: TraceQuality = "accurate") -> CubeMap:
        """The cube map of ``kind`` at a position, traced there or blended (``method`` and
        ``quality``, see :meth:`map_at`).

        ``level=None`` fetches every level (the whole specular chain as one CubeMap); an integer
        fetches that level alone.
        """
        levels = self._levels_wanted(grid, kind, level)
        if levels is None:
            self.grid(grid)
            levels = self._levels_wanted(grid, kind, level) or [0]
        faces = [
            _load_npy(self._send(self._map_call(grid, position, normal, kind, k, method,
                                                quality)))
            for k in levels
        ]
        return CubeMap(tuple(faces), kind=kind)

    def shade(self, grid: str, points: ArrayLike, normals: ArrayLike, views: ArrayLike, *,
              albedo: ArrayLike = (1.0, 1.0, 1.0), f0: ArrayLike = (0.04, 0.04, 0.04),
              roughness: ArrayLike = 0.5, batch_size: int = 1024) -> NDArray[np.float32]:
        """Split-sum shading of surface points; ``(n, 3)`` float32 radiance.

        ``albedo`` and ``f0`` are ``(3,)`` or ``(n, 3)``, ``roughness`` scalar or ``(n,)``;
        requests carry ``batch_size`` points each.
        """
        calls = self._shade_calls(grid, points, normals, views, albedo=albedo, f0=f0,
                                  roughness=roughness, batch_size=batch_size)
        return np.concatenate([self._shade_result(self._send(c)) for c in calls])

    def light_maps(self, position: ArrayLike, lights: Sequence[Light], *,
                   kind: Literal["diffuse", "specular"] = "diffuse", level: int = 0,
                   grid: str | None = None, diffuse_size: int = 16, specular_size: int = 32,
                   specular_levels: int | None = None, normal: ArrayLike | None = None
                   ) -> CubeMap:
        """Analytic map (one level) of dynamic lights at a position, plus ``grid``'s map if given
        (blended visibility-aware with the surface ``normal``, as :meth:`maps_at`)."""
        call = self._light_call(position, lights, kind=kind, level=level, grid=grid,
                                diffuse_size=diffuse_size, specular_size=specular_size,
                                specular_levels=specular_levels, normal=normal)
        return CubeMap((_load_npy(self._send(call)),), kind=kind)


# ------------------------------------------------------------------------------ async client
class AsyncProbeGridClient(_BaseClient):
    """``async`` twin of :class:`ProbeGridClient`: same options, same methods, awaited."""

    def __init__(
        self,
        base_url: str,
        *,
        timeout: float | httpx.Timeout = 10.0,
        retries: int = 2,
        backoff: float = 0.1,
        headers: dict[str, str] | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, timeout=timeout, retries=retries, backoff=backoff,
                         headers=headers)
        self._http = httpx.AsyncClient(base_url=self.base_url, timeout=self._timeout,
                                       headers=self._headers, transport=transport)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _send(self, call: _Call) -> httpx.Response:
        failure: ProbeGridError | None = None
        for delay in self._delays():
            if delay:
                await asyncio.sleep(delay)
            try:
                response = await self._http.request(call.method, call.path,
                                                    **self._request_kwargs(call))
            except httpx.TransportError as exc:
                failure = self._transport_failure(exc, call)
                continue
            failure = self._response_failure(response)
            if failure is None:
                return response
        assert failure is not None
        raise failure

    async def healthz(self) -> bool:
        r = await self._send(_Call("GET", "/healthz"))
        with _decoding(r):
            return r.json().get("status") == "ok"

    async def grids(self) -> list[GridInfo]:
        return self._grids_result(await self._send(self._grids_call()))

    async def grid(self, name: str) -> GridInfo:
        return self._grid_result(await self._send(self._grid_call(name)))

    async def sh_at(self, grid: str, position: ArrayLike, *, normal: ArrayLike | None = None,
                    sh: Literal["deringed", "raw"] = "deringed",
                    source: Literal["field", "probes"] = "field") -> SHSample:
        return self._sh_result(await self._send(self._sh_call(grid, position, normal, sh,
                                                              source)))

    async def map_at(self, grid: str, position: ArrayLike, *, kind: MapKind = "diffuse",
                     level: int = 0, normal: ArrayLike | None = None,
                     method: MapMethod = "trace", quality: TraceQuality = "accurate"
                     ) -> MapSample:
        r = await self._send(self._map_call(grid, position, normal, kind, level, method,
                                            quality))
        return self._map_sample(r, kind, int(level))

    async def maps_at(self, grid: str, position: ArrayLike, *, kind: MapKind = "diffuse",
                      level: int | None = None, normal: ArrayLike | None = None,
                      method: MapMethod = "trace", quality: TraceQuality = "accurate"
                      ) -> CubeMap:
        levels = self._levels_wanted(grid, kind, level)
        if levels is None:
            await self.grid(grid)
            levels = self._levels_wanted(grid, kind, level) or [0]
        responses = await asyncio.gather(
            *(self._send(self._map_call(grid, position, normal, kind, k, method, quality))
              for k in levels)
        )
        return CubeMap(tuple(_load_npy(r) for r in responses), kind=kind)

    async def shade(self, grid: str, points: ArrayLike, normals: ArrayLike, views: ArrayLike, *,
                    albedo: ArrayLike = (1.0, 1.0, 1.0), f0: ArrayLike = (0.04, 0.04, 0.04),
                    roughness: ArrayLike = 0.5, batch_size: int = 1024) -> NDArray[np.float32]:
        calls = self._shade_calls(grid, points, normals, views, albedo=albedo, f0=f0,
                                  roughness=roughness, batch_size=batch_size)
        responses = await asyncio.gather(*(self._send(c) for c in calls))
        return np.concatenate([self._shade_result(r) for r in responses])

    async def light_maps(self, position: ArrayLike, lights: Sequence[Light], *,
                         kind: Literal["diffuse", "specular"] = "diffuse", level: int = 0,
                         grid: str | None = None, diffuse_size: int = 16,
                         specular_size: int = 32, specular_levels: int | None = None,
                         normal: ArrayLike | None = None) -> CubeMap:
        call = self._light_call(position, lights, kind=kind, level=level, grid=grid,
                                diffuse_size=diffuse_size, specular_size=specular_size,
                                specular_levels=specular_levels, normal=normal)
        return CubeMap((_load_npy(await self._send(call)),), kind=kind)
