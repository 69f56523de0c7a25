"""The bounce schedule: which passes a bake runs, what each reads, when it stops
(probegrid.bake.schedule)."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake.converge import convergence
from probegrid.bake.schedule import BounceSchedule
from probegrid.bake.settings import BakeSettings


def _run(schedule: BounceSchedule, energies: list[float]) -> list[int]:
    """Drive ``schedule`` as the driver does, the grid of level k having energy ``energies[k]``;
    returns the levels of the passes it ran."""
    schedule.passed(energies[0])
    ran = []
    while (k := schedule.next_pass()) is not None:
        ran.append(k)
        schedule.passed(energies[k])
    return ran


@pytest.mark.parametrize(("bounces", "gather_samples", "passes"),
                         [(0, 8, []), (1, 8, []), (3, 8, []), (5, 8, [1, 2]), (3, 0, [1, 2])])
def test_a_fixed_count_makes_the_grids_its_final_pass_reads(bounces, gather_samples, passes):
    """``bounces = B``: the passes make the grids up to the one the final pass at B reads."""
    schedule = BounceSchedule.of(BakeSettings(bounces=bounces, gather_samples=gather_samples))
    assert _run(schedule, [1.0] * 10) == passes
    assert schedule.level == bounces and schedule.passes == len(passes)
    assert schedule.residual is None and not schedule.extrapolates
    assert schedule.label(0) == f"bounce 0 of {bounces} (tracing)"
    assert schedule.label(bounces, final=True) == f"bounce {bounces} of {bounces} (final)"
    assert schedule.reads(bounces) == bounces - 1 - schedule.depth


def test_a_converging_bake_stops_by_the_rule_and_reads_the_extrapolated_grid():
    """The passes go on until :func:`probegrid.bake.converge.convergence` says stop; the final
    level is the last pass's plus the step, and the final pass reads the grid's limit."""
    st = BakeSettings(bounces="converge", tolerance=1e-3)
    schedule = BounceSchedule.of(st)
    e = [1.0]
    d = 1.0
    for _ in range(40):
        e.append(e[-1] + d)
        d *= 0.6
    assert schedule.label(0) == "tracing: bounce 0"
    ran = _run(schedule, e)
    k = ran[-1]
    assert ran == list(range(1, k + 1)) and schedule.passes == k
    expected = convergence(e[:k + 1], st.tolerance, schedule.period)
    assert expected.done and schedule.state == expected
    assert not convergence(e[:k], st.tolerance, schedule.period).done
    assert schedule.level == k + schedule.step
    assert schedule.extrapolates
    grids = {j: np.full((2, 6, 1, 1, 3), e[j], np.float32) for j in range(k + 1)}
    limit = schedule.limit(grids)
    assert limit.dtype == np.float32
    assert limit.flat[0] == pytest.approx(expected.limit, rel=1e-6)
    assert schedule.label(schedule.level, final=True).startswith(
        f"converged: bounce {schedule.level}, residual ")


def test_a_converging_bake_stops_at_its_most_bounces():
    schedule = BounceSchedule.of(BakeSettings(bounces="converge", max_bounces=4))
    ran = _run(schedule, [float(j + 1) for j in range(10)])  # never converges
    assert schedule.level == 4 and ran == list(range(1, 4 - schedule.step + 1))
