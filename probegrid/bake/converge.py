"""When ``--bounces converge`` stops, and the limit it extrapolates to.

A bake's bounces add light in a series: the grid of bounce ``k`` holds ``G_k = G_{k-1} + D_k``
with every ``D_k >= 0`` (the same records replayed with one more reflection), and the grid's
total energy ``E_k`` follows. Far enough along, the increments shrink geometrically: light
bounces between the same surfaces with the same mean albedo. With final gather (the default)
a pass reads the grid ``p = 1 + depth`` levels down (``depth`` gather levels), so the
increments cycle through ``p`` ratios (with one gather level on the sample room: 0.58, 0.63,
0.58, ...); the *groups* ``S_k = E_k - E_{k-p}`` shrink with one ratio ``q = S_k / S_{k-p}``
(``p = 2`` at least: a plain geometric series is one too). The remaining tail is then
``S_k (q + q^2 + ...) = S_k q / (1 - q)``, so

    E_inf ~ E_k + S_k f,   G_inf ~ G_k + (G_k - G_{k-p}) f,   f = q / (1 - q),

the same per texel as for the total (the increments are non-negative, so the limit is never
below ``G_k``). Aitken's extrapolation of the series, per group.

The bake stops when two successive estimates of ``E_inf`` differ by less than the tolerance
(relative): measured over 40 bounces of the sample room and the Cornell box, that difference
tracks the estimate's own error within 1.5x, and the estimate at the stop is 6e-4 and 5e-4 off
the limit where stopping on the raw increment (``(E_k - E_{k-1}) / E_k < 0.1 %``) needed 12 and
8 passes and was still 1.5e-3 and 1.6e-4 short. The final pass then reads the extrapolated grid.
A series that stops changing (no surface reflects: both increments of a pair are 0) stops
without extrapolating, as does a grid with no light.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MIN_PASSES", "Convergence", "convergence"]

#: Passes before the extrapolation by pairs can be compared with the previous one (E_0 .. E_5);
#: groups of ``p`` need ``2 p + 1``.
MIN_PASSES = 5


@dataclass(frozen=True)
class Convergence:
    """Where a converging bake stands after bounce ``k``.

    Attributes
    ----------
    done : bool
        Stop now.
    residual : float or None
        Relative change of the estimated limit (or of the raw energy before there is an
        estimate); None before the second pass.
    factor : float or None
        ``f = q / (1 - q)`` to extrapolate ``G_k + (G_k - G_{k-p}) f``, when extrapolating.
    limit : float or None
        The estimated limit of the energy.
    """

    done: bool
    residual: float | None
    factor: float | None = None
    limit: float | None = None


def _estimate(e: list[float], k: int, period: int = 2) -> tuple[float, float] | None:
    """``(E_inf, f)`` from ``e[k-2p] .. e[k]``, or None when the groups are not shrinking."""
    p = period
    s, s2 = e[k] - e[k - p], e[k - p] - e[k - 2 * p]
    if not (s >= 0 and s2 > 0 and s < s2):
        return None
    q = s / s2
    f = q / (1.0 - q)
    return e[k] + s * f, f


def convergence(energies: list[float], tolerance: float, period: int = 2) -> Convergence:
    """Whether the bounce series of ``energies`` (``E_0 .. E_k``, one per pass) has converged
    to ``tolerance`` (relative), and how to extrapolate its grid, in groups of ``period``
    increments (module docstring)."""
    k = len(energies) - 1
    if k < 1:
        return Convergence(False, None)
    e = [float(x) for x in energies]
    if e[k] <= 0.0:  # no light to bounce
        return Convergence(True, 0.0)
    raw = abs(e[k] - e[k - 1]) / e[k]
    if k >= 2 and e[k] == e[k - 1] == e[k - 2]:  # nothing reflects any more
        return Convergence(True, 0.0)
    if k < 2 * period + 1:
        return Convergence(False, raw)
    now, before = _estimate(e, k, period), _estimate(e, k - 1, period)
    if now is None or before is None:  # not (yet) geometric: go on, on the raw change
        return Convergence(raw < 0.1 * tolerance, raw)
    change = abs(now[0] - before[0]) / now[0]
    return Convergence(change < tolerance, change, now[1], now[0])
