"""Settings of the probe map service, from keyword arguments or ``PROBEGRID_*`` environment variables.

One :class:`Settings` object configures an app (:func:`service.main.create_app`). Every field can
also be set from the environment with the prefix ``PROBEGRID_`` (``PROBEGRID_MAX_BATCH=1024``);
list fields take JSON (``PROBEGRID_STORES='["a.probes", "b.probes"]'``). The limits bound the
work and memory one request can cause; a request over a limit gets a 4xx JSON error naming it.

:func:`settings_environment` turns a settings object back into those variables, which is how
:func:`service.main.run` hands its settings and store list to uvicorn worker processes.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["ENV_PREFIX", "Settings", "load_settings", "settings_environment"]

ENV_PREFIX = "PROBEGRID_"


class Settings(BaseSettings):
    """Service configuration (immutable).

    Attributes
    ----------
    stores : list of Path
        Store directories to serve when the app is built from the environment (worker processes).
        :func:`service.main.create_app` takes its stores as an argument instead.
    max_body_bytes : int
        Largest request body accepted, in bytes (413 above it).
    max_batch : int
        Most points one ``POST /v1/grids/{grid}/shade`` may carry (413 above it).
    max_lights : int
        Most lights one ``POST /v1/lights/maps`` may carry (422 above it).
    max_light_map_size : int
        Largest face size, in texels, a request may ask analytic light maps for (422 above it).
    max_json_values : int
        Most floats a ``format=json`` map response may hold (422 above it; use npy or exr).
        The default holds a cube of the default ``max_light_map_size`` (``6 x 256^2 x 3``), so
        that with the defaults every light map may be asked for as JSON.
    max_heavy_requests : int
        Most ``POST /v1/lights/maps`` and ``POST /v1/grids/{grid}/shade`` requests one process
        runs at once (each may take seconds of CPU); one more is answered ``503 busy`` with
        ``Retry-After`` at once instead of queueing behind them.
    request_budget : float
        Most seconds of CPU one request may cost, as :mod:`service.cost` estimates it from the
        request before any work (``POST /v1/lights/maps`` and ``/shade``; ``422 over_budget``
        above it). The default, 2 s, holds 16 lights' full specular chain of face 32, or one
        light's of face 256.
    header_timeout : float
        Seconds a connection may take to send a request's line and headers, from its opening
        or the end of its previous response (a slow or idle client is then answered ``408``
        and closed; :mod:`service.protocol`).
    body_timeout : float
        Seconds a request may take to send its body once its headers are in (``408`` and
        closed after that).
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, frozen=True, extra="ignore")

    stores: list[Path] = Field(default_factory=list)
    max_body_bytes: int = Field(default=1 << 20, ge=1024)
    max_batch: int = Field(default=4096, ge=1)
    max_lights: int = Field(default=16, ge=1)
    max_light_map_size: int = Field(default=256, ge=1)
    max_json_values: int = Field(default=6 * 256 * 256 * 3, ge=1)
    max_heavy_requests: int = Field(default=2, ge=1)
    request_budget: float = Field(default=2.0, gt=0.0, allow_inf_nan=False)
    header_timeout: float = Field(default=10.0, gt=0.0, le=3600.0, allow_inf_nan=False)
    body_timeout: float = Field(default=30.0, gt=0.0, le=3600.0, allow_inf_nan=False)


def settings_environment(settings: Settings) -> dict[str, str]:
    """The ``PROBEGRID_*`` environment variables that rebuild ``settings`` in another process.

    Returns
    -------
    dict of str to str
        One variable per field, values JSON-encoded (``Settings()`` parses them back).
    """
    data = settings.model_dump(mode="json")
    return {f"{ENV_PREFIX}{k.upper()}": json.dumps(v) for k, v in data.items()}


def load_settings() -> Settings:
    """``Settings()`` from the ``PROBEGRID_*`` environment, with a one-line ValueError naming
    the variable when one does not parse (instead of pydantic's multi-line report)."""
    try:
        return Settings()
    except ValidationError as exc:
        err = exc.errors()[0]
        name = ENV_PREFIX + str(err["loc"][0]).upper() if err.get("loc") else ENV_PREFIX + "*"
        raise ValueError(f"environment variable {name}: {err['msg']}.") from None
