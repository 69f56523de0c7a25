"""The padded equirect lookup of to_cube equals the reference bilinear lookup (probegrid.core.layouts)."""

from __future__ import annotations

import numpy as np

from probegrid.core import layouts as L


def test_padded_lookup_equals_the_wrapping_bilinear_lookup():
    rng = np.random.default_rng(4)
    img = rng.random((16, 32, 3)).astype(np.float32)
    d = rng.normal(size=(20000, 3))
    # the poles, the seam of the longitude wrap and points just across it, near-pole rings
    d[:6] = [[0, 1, 0], [0, -1, 0], [-1, 0, 1e-12], [-1, 0, -1e-12], [1, 0, 0], [0, 0, 1]]
    d[6:1000] = rng.normal(size=(994, 3)) * [0.02, 1.0, 0.02]
    x, y = L.direction_to_equirect(d, 16, 32)
    ref = L._equirect_bilinear(img, x, y)
    got = L._EquirectLookup(img)(d)
    np.testing.assert_allclose(got, ref, atol=2e-4)  # float32 angles: ~1e-5 pixel here

