"""Random triangle soups for the tests of the compiled surface kernels (scene and bake)."""

from __future__ import annotations

import numpy as np


def triangle_soup(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """30 random vertices, 40 triangles of them, their unit normals as wound and one of 3
    materials each."""
    verts = rng.normal(size=(30, 3))
    tris = np.stack([rng.permutation(30)[:3] for _ in range(40)]).astype(np.int64)
    p = verts[tris]
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return verts, tris, nrm, rng.integers(0, 3, 40).astype(np.int64)
