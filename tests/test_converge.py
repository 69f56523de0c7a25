"""When a converging bake stops and the limit it extrapolates to (probegrid.bake.converge)."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake.converge import MIN_PASSES, convergence


def _series(ratios, n, e0=1.0, d1=1.0):
    """Energies E_0 .. E_n whose increments cycle through ``ratios``."""
    e, d = [e0], d1
    for k in range(n):
        e.append(e[-1] + d)
        d *= ratios[k % len(ratios)]
    return e


@pytest.mark.parametrize("ratios", [(0.6,), (0.58, 0.63), (0.3, 0.9), (0.5, 0.7, 0.6)])
def test_a_geometric_series_of_groups_is_extrapolated_to_its_limit(ratios):
    """Increments cycling through p ratios (a pass reads the grid p levels down) have groups of
    p shrinking by their product: the estimate is the exact limit, and the run stops at the
    first comparison."""
    p = max(len(ratios), 2)
    e = _series(ratios, 2 * p + 1)
    c = convergence(e, 1e-3, p)
    q = np.prod(ratios) if len(ratios) == p else ratios[0] ** p
    # the limit of the series: E_0 + d1 * (1 + r1 + r1 r2 + ...) summed in closed form
    long = _series(ratios, 400)
    assert c.done and c.limit == pytest.approx(long[-1], rel=1e-12)
    assert c.factor == pytest.approx(q / (1 - q), rel=1e-12)
    assert c.residual == pytest.approx(0.0, abs=1e-12)


def test_it_goes_on_until_the_estimate_settles():
    """A series whose ratio still drifts is not stopped by a small raw increment alone."""
    rng = np.random.default_rng(2)
    e = [1.0]
    d = 1.0
    stops = None
    for k in range(1, 60):
        e.append(e[-1] + d)
        d *= 0.9 - 0.4 / (k + 1) + 0.01 * rng.random()
        c = convergence(e, 1e-4)
        if c.done:
            stops = k
            break
    assert stops is not None and stops > MIN_PASSES
    assert abs(c.limit - e[-1]) / c.limit < 0.2  # a real tail remains, estimated
    assert (e[-1] - e[-2]) / e[-1] > 1e-4  # where the raw increment rule had not stopped


def test_no_light_and_nothing_to_reflect_stop_at_once():
    assert convergence([0.0, 0.0], 1e-3).done
    c = convergence([5.0, 5.0, 5.0], 1e-3)
    assert c.done and c.factor is None and c.residual == 0.0
    assert not convergence([5.0], 1e-3).done
    c = convergence([1.0, 1.5, 1.7], 1e-3)
    assert not c.done and c.residual == pytest.approx(0.2 / 1.7)
