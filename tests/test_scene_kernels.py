"""The compiled surface lookups of the scene (:mod:`probegrid.scene.kernels`) against the numpy
expressions they restate."""

from __future__ import annotations

import numpy as np
import pytest
from meshes import triangle_soup


@pytest.mark.parametrize("wrap,transform", [
    (("repeat", "repeat"), None), (("clamp", "mirror"), None), (("mirror", "clamp"), None),
    (("repeat", "mirror"), ((0.25, -0.5), 0.7, (2.0, -1.5)))])
def test_texture_kernel_matches_sample_texture(wrap, transform) -> None:
    from probegrid.scene.kernels import multiply_texture
    from probegrid.scene.textures import _WRAPS, TexCoord, sample_texture, texture_transform

    rng = np.random.default_rng(5)
    tex = rng.random((5, 7, 4)).astype(np.float32)
    tris = np.array([[0, 1, 2], [1, 3, 2]], dtype=np.int64)
    uvs = rng.uniform(-2.0, 3.0, (4, 2))
    n = 500
    prim = rng.integers(0, 2, n).astype(np.int64)
    bu = rng.random(n)
    bv = rng.random(n) * (1 - bu)
    w = np.stack([1 - bu - bv, bu, bv], axis=1)[:, :, None]
    uv = np.sum(w * uvs[tris[prim]], axis=1)
    tc = TexCoord() if transform is None else texture_transform(*transform)
    uv = tc.apply(uv)
    xform = np.zeros(0) if transform is None else np.array(tc.matrix)
    target = rng.random((n, 3)) + 0.5
    alpha = rng.random(n) + 0.5
    rows = np.flatnonzero(rng.random(n) < 0.7)
    expect = target.copy()
    expect_alpha = alpha.copy()
    expect[rows] *= sample_texture(tex, uv[rows], wrap=wrap)[:, :3]
    expect_alpha[rows] *= sample_texture(tex, uv[rows], wrap=wrap)[:, 3]
    wraps = (_WRAPS.index(wrap[0]), _WRAPS.index(wrap[1]))
    multiply_texture(target, rows, (prim, bu, bv), tris, uvs, tex, wraps, xform, 0)
    multiply_texture(alpha.reshape(-1, 1), rows, (prim, bu, bv), tris, uvs, tex, wraps, xform, 3)
    np.testing.assert_allclose(target, expect, rtol=1e-12)
    np.testing.assert_allclose(alpha, expect_alpha, rtol=1e-12)


def test_texture_transform_follows_the_extension_example() -> None:
    """KHR_texture_transform's example (offset (0, 1), rotation pi/2, scale 0.5) reads "the
    lower left quadrant of the source image, rotated clockwise 90 degrees": the unit square's
    corners land on that quadrant's (v grows downward)."""
    from probegrid.scene.textures import texture_transform

    tc = texture_transform((0.0, 1.0), np.pi / 2, (0.5, 0.5))
    corners = tc.apply([[0, 0], [1, 0], [1, 1], [0, 1]])
    np.testing.assert_allclose(corners, [[0, 1], [0, 0.5], [0.5, 0.5], [0.5, 1]], atol=1e-12)


def test_hit_surfaces_match_numpy_with_vertex_colors() -> None:
    from probegrid.scene.kernels import SurfaceTables, hit_surfaces

    rng = np.random.default_rng(6)
    verts, tris, nrm, material = triangle_soup(rng)
    base = rng.random((3, 3))
    emis = rng.random((3, 3))
    colors = rng.random((30, 4))
    n = 500
    prim = rng.integers(0, 40, n).astype(np.int64)
    u = rng.random(n)
    v = rng.random(n) * (1 - u)
    pos, nn, alb, em = hit_surfaces(prim, u, v, SurfaceTables(
        verts, tris, nrm, material, base, emis, np.ascontiguousarray(colors[:, :3])))
    w = np.stack([1 - u - v, u, v], axis=1)[:, :, None]
    np.testing.assert_allclose(pos, np.sum(w * verts[tris[prim]], axis=1), rtol=1e-13,
                               atol=1e-14)
    np.testing.assert_array_equal(nn, nrm[prim])
    np.testing.assert_allclose(alb, base[material[prim]]
                               * np.sum(w * colors[tris[prim]][:, :, :3], axis=1), rtol=1e-13)
    np.testing.assert_array_equal(em, emis[material[prim]])


def test_textures_apply_to_the_given_rows_only() -> None:
    """Scene.apply_textures with rows (what the records pass uses): the same products as on
    the rows' own arrays, other rows (misses, prim -1) untouched."""
    from probegrid.scene import Material, SceneBuilder

    rng = np.random.default_rng(17)
    b = SceneBuilder()
    tex = rng.random((4, 4, 4)).astype(np.float32)
    m = b.add_material(Material(base_color=(0.8, 0.7, 0.6, 1.0), base_color_texture=tex,
                                emissive=(0.5, 0.5, 0.5), emissive_texture=tex[..., :3]))
    b.add_quad((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), material=m)
    scene = b.build()
    n = 50
    prim = np.where(rng.random(n) < 0.3, -1, rng.integers(0, scene.n_triangles, n))
    u = rng.random(n)
    v = rng.random(n) * (1 - u)
    rows = np.flatnonzero(prim >= 0)
    alb, emi = rng.random((n, 3)), rng.random((n, 3))
    alb_r, emi_r = alb[rows].copy(), emi[rows].copy()
    scene.apply_textures(prim[rows], u[rows], v[rows], alb_r, emi_r)
    before_a, before_e = alb.copy(), emi.copy()
    scene.apply_textures(prim, u, v, alb, emi, rows)
    np.testing.assert_array_equal(alb[rows], alb_r)
    np.testing.assert_array_equal(emi[rows], emi_r)
    miss = prim < 0
    np.testing.assert_array_equal(alb[miss], before_a[miss])
    np.testing.assert_array_equal(emi[miss], before_e[miss])
    assert not np.array_equal(alb_r, before_a[rows])
