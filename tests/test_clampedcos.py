"""The hierarchical clamped-cosine sum equals the dense sum over every texel (probegrid.core)."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core.clampedcos import clamped_cosine_sum
from probegrid.core.cubemap import texel_directions, texel_solid_angles


def dense(faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    w = texel_directions(faces.shape[1]).reshape(-1, 3)
    lw = faces.reshape(-1, faces.shape[3]).astype(np.float64) * texel_solid_angles(
        faces.shape[1]).reshape(-1, 1)
    return np.maximum(normals @ w.T, 0.0) @ lw


@pytest.mark.parametrize("top, finest", [(8, None), (2, 4), (16, 32), (1, 16)])
def test_equals_the_dense_sum_for_any_levels(top, finest):
    rng = np.random.default_rng(3)
    faces = rng.random((6, 32, 32, 2)) - 0.2           # some negative radiance too
    faces[2, 5, 7] = 500.0                              # a sun
    faces[4, 31, 0] = 80.0                              # at a cube corner
    normals = rng.normal(size=(700, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.concatenate([normals, texel_directions(8).reshape(-1, 3),
                              np.eye(3), -np.eye(3)])   # also exactly on axes and texel centres
    ref = dense(faces, normals)
    got = clamped_cosine_sum(faces, normals, top=top, finest=finest)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_bad_sizes():
    with pytest.raises(ValueError, match="power of two"):
        clamped_cosine_sum(np.ones((6, 12, 12, 1)), np.eye(3))
