"""The cost model of the requests whose work depends on what they ask: estimated before any work.

``POST /v1/lights/maps`` and ``POST /v1/grids/{grid}/shade`` are the two routes whose cost
grows with the request (lights, face sizes, levels; points). Each is estimated from the request
alone, in seconds of CPU on the reference machine, and refused over
:attr:`service.settings.Settings.request_budget` with ``422 over_budget``, a message naming
the budget, the setting, the estimate and the parameters to lower, before any of its work is
done. Every other route costs what the store's sizes fix (a ``/maps`` trace renders one probe
with the bake's settings; ``/sh`` blends 8 probes), whatever the request.

Model
-----
* Light maps: :func:`probegrid.core.lights.light_maps_work` counts the texels of every
  (subdivided) cube :func:`~probegrid.core.lights.light_maps` fills and its lobe-kernel
  evaluations (texels x lights); the time is
  ``SECONDS_PER_TEXEL texels + SECONDS_PER_EVALUATION evaluations`` (every light counted as lit:
  an upper bound).
* Shading: ``SECONDS_PER_SHADED_POINT`` a point (its weights with 8 visibility segments and the
  blended diffuse and specular lookups), whatever the store's sizes (bilinear lookups).

The constants are measured on the project's reference machine (2 cores, shared) by
``benchmarks/bench_service_cost.py``, which prints the model's estimate over the measured CPU
time for a range of requests; docs/benchmarks.md has the figures. On a faster machine the model
is conservative; the budget is a setting either way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from probegrid.core.lights import light_maps_work
from service.errors import ApiError

__all__ = [
    "SECONDS_PER_EVALUATION",
    "SECONDS_PER_SHADED_POINT",
    "SECONDS_PER_TEXEL",
    "Estimate",
    "check_budget",
    "light_maps_estimate",
    "shade_estimate",
]

#: CPU seconds per texel of a light map's subdivided cubes (directions, solid angles, sums).
SECONDS_PER_TEXEL: Final = 95e-9
#: CPU seconds per lobe-kernel evaluation (one texel, one light).
SECONDS_PER_EVALUATION: Final = 200e-9
#: CPU seconds per shaded point.
SECONDS_PER_SHADED_POINT: Final = 60e-6


@dataclass(frozen=True)
class Estimate:
    """A request's estimated cost: ``seconds`` of CPU, what it counts (``work``, in words) and
    the request parameters that raise it (``parameters``, named as the request names them)."""

    seconds: float
    work: str
    parameters: str


def light_maps_estimate(n_lights: int, *, diffuse_size: int, specular_size: int,
                        specular_levels: int | None) -> Estimate:
    """The cost of :func:`probegrid.core.lights.light_maps` with these arguments.

    Raises
    ------
    ValueError
        A face size or chain ``light_maps`` refuses.
    """
    work = light_maps_work(n_lights, diffuse_size=diffuse_size, specular_size=specular_size,
                           specular_levels=specular_levels)
    seconds = SECONDS_PER_TEXEL * work.texels + SECONDS_PER_EVALUATION * work.evaluations
    return Estimate(seconds=seconds,
                    work=f"{work.evaluations / 1e6:.3g} M lobe evaluations, {n_lights} "
                         f"lights over {work.texels / 1e6:.3g} M texels",
                    parameters="lights, diffuse_size, specular_size or specular_levels")


def shade_estimate(n_points: int) -> Estimate:
    """The cost of shading ``n_points`` points (:meth:`probegrid.query.ProbeField.shade`)."""
    return Estimate(seconds=SECONDS_PER_SHADED_POINT * n_points,
                    work=f"{n_points} shaded points", parameters="points")


def check_budget(estimate: Estimate, budget: float) -> None:
    """Raise ``ApiError 422 over_budget`` when ``estimate`` is over ``budget`` seconds."""
    if estimate.seconds > budget:
        raise ApiError(
            422,
            f"The request would take about {estimate.seconds:.3g} s of CPU "
            f"({estimate.work}), over the budget of {budget:g} s per request "
            "(request_budget: probegrid serve --request-budget, PROBEGRID_REQUEST_BUDGET); "
            f"lower {estimate.parameters}",
            code="over_budget",
        )
