"""A probe's own texels: sub-texel patterns sampled to their area, no block edges in the maps
(probegrid.bake.pattern, probegrid.bake.records.replay._smooth_gathered)."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake.driver import BakeSettings, bake
from probegrid.core.grid import GridSpec
from probegrid.core.lights import DirectionalLight, PointLight
from probegrid.scene import Material, SceneBuilder


def block_jumps(fields: np.ndarray, block: int = 8) -> float:
    """The mean absolute difference of neighbouring texels within a face across the edges
    between ``block``-texel blocks over the same across every other edge within the faces (on
    the luminance, all faces of all probes): 1 when the blocks leave no edge. Of the difference
    of two bakes, what the scene shows cancels and the bakes' noise is left."""
    y = np.asarray(fields, np.float64).mean(axis=-1)
    n = y.shape[-1]
    dx, dy = np.abs(np.diff(y, axis=-1)), np.abs(np.diff(y, axis=-2))
    edge = (np.arange(n - 1) + 1) % block == 0

    def jumps(sel: np.ndarray) -> float:
        return float(np.concatenate([dx[..., sel].ravel(), dy[..., sel, :].ravel()]).mean())

    return jumps(edge) / jumps(~edge)


def _grating(pitch: float) -> SceneBuilder:
    """A floor (albedo 0.5, y = 0) under a sun straight down of pi lux, through a grating of
    bars at y = 3 whose shadows cover ``[k pitch + pitch / 4, k pitch + 3 pitch / 4)`` in x:
    half the floor lit, in stripes ``pitch`` apart."""
    b = SceneBuilder()
    floor = b.add_material(Material.diffuse(0.5))
    bar = b.add_material(Material.diffuse(0.5))
    b.add_quad((-3.0, 0.0, 3.0), (6.0, 0.0, 0.0), (0.0, 0.0, -6.0), material=floor)
    for k in range(-int(1.0 / pitch), int(1.0 / pitch)):
        x0 = k * pitch + pitch / 4
        b.add_quad((x0, 3.0, 3.0), (pitch / 2, 0.0, 0.0), (0.0, 0.0, -6.0), material=bar)
    b.add_light(DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0), np.pi))
    return b


@pytest.mark.parametrize("samples,tolerance", [(1, 0.10), (4, 0.03)])
def test_a_sun_grating_finer_than_a_texel_is_seen_at_its_area_fraction(tmp_path, samples,
                                                                       tolerance):
    """A probe half a metre above the floor looks down through its -Y face (32^2), whose
    texels' centres fall 1/32 apart on the floor, exactly the grating's pitch, all in the
    bars' shadows: rays through the texel centres see a black floor. Every texel covers one
    period, half of it lit: each holds 0.25 (0.5 E / pi, half lit). Rays placed anywhere in
    their texels, each texel its own offset, see it so on average: the face's mean within 10 %
    with one ray per texel (binomial: 3 % standard deviation over 1024 texels), within 3 % with
    four stratified ones."""
    scene = _grating(1.0 / 32).build()
    grid = GridSpec.from_counts((0.0, 0.5, 0.0), (0.0, 0.5, 0.0), (1, 1, 1))
    st = BakeSettings(face_size=32, samples=samples, bounces=0, diffuse_size=4,
                      moments_size=4, store_incoming=True)
    s = bake(scene, grid, tmp_path / "g.probes", settings=st).store
    below = np.asarray(s["incoming"][0, 3], np.float64)  # the -Y face: the floor only
    assert abs(below.mean() / 0.25 - 1.0) < tolerance
    # the stripes reach the texels as they lie: every texel holds 0 or 0.5 with one ray
    if samples == 1:
        assert set(np.unique(np.round(below, 6))) <= {0.0, 0.5}


def test_the_gathers_smoothing_leaves_no_block_edges(tmp_path):
    """In a closed box lit by a point light (bounce 3 reads the grid: the gather's correction
    is smoothed over each probe's texels), the noise of the incoming cube -- two seeds' bakes
    apart -- jumps across the edges of 8 x 8 texel blocks no more than across other edges (a
    mean correction per block made it a step function of the blocks: 15-16x)."""
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.7))
    b.add_box((-2, 0, -2), (2, 3, 2), material=m, inward=True)
    b.add_light(PointLight((0.5, 2.5, 0.3), (1.0, 1.0, 1.0), 20.0))
    grid = GridSpec.from_counts((-1, 0.75, -1), (1, 2.25, 1), (2, 2, 2))
    cubes = []
    for seed in (0, 1):
        st = BakeSettings(face_size=16, diffuse_size=4, moments_size=4, bounces=3, seed=seed,
                          store_incoming=True)
        s = bake(b.build(), grid, tmp_path / f"b{seed}.probes", settings=st).store
        cubes.append(np.asarray(s["incoming"], np.float64))
    assert block_jumps(cubes[0] - cubes[1]) < 1.1
