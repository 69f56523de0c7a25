"""The final gather from the surface light cache (probegrid.bake.finalgather).

The cache's indirect light iterated on itself reaches a furnace box's analytic
``rho Le / (1 - rho)`` whatever the grid it started from (a black grid read at the deepest
gather hits leaves two gather levels at ``rho Le (1 + rho)``); a bake with a final gather
reads ``Le / (1 - rho)`` at its probes, is the same bits on one process and on two with other
batches, and resumes bit for bit after an interrupt inside its final pass.
"""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake import BakeSettings, bake
from probegrid.bake.environment import Environment
from probegrid.bake.executors import InlineExecutor, LocalExecutor
from probegrid.bake.records import GridData
from probegrid.bake.finalgather import FINAL_GATHER_RAYS, final_gather_plan
from probegrid.bake.surfacecache import bake_surface_cache, plan_lattice
from probegrid.core.ddgi import bordered_cubes
from probegrid.core.grid import GridSpec
from probegrid.core.lights import PointLight
from probegrid.scene import box_scene
from test_bake import _StopInMap  # (Ctrl-C after a map's first batch)

FAST = {"face_size": 8, "diffuse_size": 4, "moments_size": 4, "batch_size": 4}
RHO, LE = 0.5, 2.0


def _furnace():
    return box_scene((-1, -1, -1), (1, 1, 1), albedo=RHO, emission=LE, inward=True)


def _arrays(store):
    return {name: np.asarray(store.arrays[name])
            for name in [*store.names, *store.manifest.extras]}


@pytest.mark.parametrize("iterations", [0, 12])
def test_the_iterated_cache_reaches_the_furnace_limit_from_a_black_grid(iterations):
    """Two gather levels over a black grid hold ``rho Le (1 + rho)``; gathered again from the
    cache itself, the indirect light converges to ``rho Le / (1 - rho)`` (the error shrinks
    by ``rho`` per iteration: 2.4e-4 after 12)."""
    scene = _furnace()
    st = BakeSettings(bounces="converge", **FAST)
    geometry = st.trace_geometry(scene, GridSpec.from_counts((-0.5,) * 3, (0.5,) * 3,
                                                             (1, 1, 1)))
    grid = GridSpec.from_counts((-0.5,) * 3, (0.5,) * 3, (1, 1, 1))
    m = st.moments_face_size
    moments = bordered_cubes(np.ones((1, 6, m, m, 2), np.float32))
    data = GridData(grid, np.ones(1, bool), np.zeros((1, 3)),
                    moments.reshape(-1, 2), m, None)  # a black grid
    got = bake_surface_cache(scene, Environment(), st, geometry, data, level=30,
                             plan=plan_lattice(scene, max_vertices=200),
                             iterations=iterations, gather=FINAL_GATHER_RAYS)
    assert got is not None
    light = got[1].astype(np.float64)
    want = RHO * LE / (1 - RHO) if iterations else RHO * LE * (1 + RHO)
    np.testing.assert_allclose(light[:, 0], want, rtol=1e-3)
    np.testing.assert_allclose(light[:, 1], LE, rtol=1e-4)


def test_a_final_gather_bake_reads_the_furnace_limit(tmp_path):
    """Every texel of a probe in the furnace box sees ``Le / (1 - rho)``."""
    grid = GridSpec.from_counts((-0.5,) * 3, (0.5,) * 3, (2, 1, 1))
    st = BakeSettings(final_gather=2, store_incoming=True, **FAST)
    store = bake(_furnace(), grid, tmp_path / "f.probes", settings=st).store
    np.testing.assert_allclose(np.asarray(store["incoming"], np.float64), LE / (1 - RHO),
                               rtol=2e-3)
    # the cache the final pass read, stored and stated: the final gather's lattice
    lattice = store.manifest.quality["surface_cache"]
    assert lattice["vertices"] == final_gather_plan(_furnace(), st).vertices
    assert "final gather of 2" in lattice["reason"]
    assert len(np.asarray(store.arrays["surface_light"])) == lattice["vertices"]


def test_the_final_gather_lattice_grows_with_its_rays_up_to_its_cap(monkeypatch):
    """The scene's default lattice with ``CACHE_TEXEL_VERTICES`` vertices per texel and per ray
    of the final view (at most one vertex a triangle side over that), whatever the grid, at
    most ``FINAL_GATHER_MAX_VERTICES``; an explicit spacing is kept, coarsened to that cap;
    without a final gather, the bake's own lattice."""
    from probegrid.bake import finalgather as fg
    from probegrid.bake.surfacecache import CACHE_TEXEL_VERTICES

    scene = box_scene((0, 0, 0), (10, 4, 8), albedo=0.5, inward=True)  # 12 one-sided sides
    plain = plan_lattice(scene, face_size=8)
    budgets = []
    for k in (1, 4, 16):
        p = fg.final_gather_plan(scene, BakeSettings(final_gather=k, face_size=8))
        budget = 12 + CACHE_TEXEL_VERTICES * 8 * 8 * k
        assert budget / 2 < p.vertices <= budget, k  # (as fine as fits: within one step)
        budgets.append(p.vertices)
    assert budgets[0] == plain.vertices and budgets[0] < budgets[1] < budgets[2]
    assert fg.FINAL_GATHER_MAX_VERTICES == 65536  # 300 MB of kept gather hits
    monkeypatch.setattr(fg, "FINAL_GATHER_MAX_VERTICES", 500)
    capped = fg.final_gather_plan(scene, BakeSettings(final_gather=16, face_size=8))
    assert 250 < capped.vertices <= 500
    fine = fg.final_gather_plan(scene, BakeSettings(final_gather=16,
                                                    surface_cache_spacing=0.01))
    assert fine.vertices <= 500 and "coarsened to at most 500" in fine.reason


def _room():
    return box_scene((-2, 0, -2), (2, 3, 2), albedo=0.5, emission=0.0, inward=True,
                     lights=(PointLight((0.3, 2.0, 0.2), (1.0, 0.9, 0.8), 20.0),))


@pytest.mark.slow
def test_a_final_gather_bake_is_the_same_bits_on_any_executor_and_after_an_interrupt(tmp_path):
    """One process, two processes with other batches, and a bake interrupted after the first
    batch of its final pass then resumed: the same bits, extras (the cache) included; and
    the final gather changes the maps (it is not the final pass's own view)."""
    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 1, 2))
    st = BakeSettings(bounces=2, final_gather=2, seed=3, **{**FAST, "batch_size": 2})
    a = _arrays(bake(_room(), grid, tmp_path / "a.probes", settings=st,
                     executor=InlineExecutor()).store)
    with LocalExecutor(2) as ex:
        b = _arrays(bake(_room(), grid, tmp_path / "b.probes",
                         settings=st.model_copy(update={"batch_size": 4}), executor=ex).store)
    out = tmp_path / "c.probes"
    with pytest.raises(KeyboardInterrupt):  # classify, trace, final (no bounce pass)
        bake(_room(), grid, out, settings=st, executor=_StopInMap(3))
    again = bake(_room(), grid, out, settings=st, executor=InlineExecutor())
    assert 0 < again.resumed_probes < grid.n_probes
    c = _arrays(again.store)
    assert a.keys() == b.keys() == c.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k
        assert np.array_equal(a[k], c[k]), k
    plain = _arrays(bake(_room(), grid, tmp_path / "d.probes",
                         settings=st.model_copy(update={"final_gather": 0})).store)
    assert not np.array_equal(plain["diffuse"], a["diffuse"])
    assert np.array_equal(plain["moments"], a["moments"])
