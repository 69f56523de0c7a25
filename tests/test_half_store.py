"""Half-float map arrays: ``--dtype half`` stores the diffuse, specular and
incoming maps as float16 (the float32 bake's values rounded to the nearest half, values beyond
65504 clamped), records it in the manifest, reads back transparently in float32, and the bake
says what each choice costs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from probegrid.bake import BakeSettings, bake
from probegrid.bake.precision import HALF_MAX, fit_map_dtype
from probegrid.bake.settings import store_bytes
from probegrid.core.grid import GridSpec
from probegrid.jobs.progress import size_note
from probegrid.query import ProbeField
from probegrid.scene import load_gltf
from probegrid.store import open_store
from probegrid.store.check import check_store

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> dict[str, Path]:
    """The sample room baked twice, inline (2x1x2 probes, faces 8, no bounce): float, half."""
    root = tmp_path_factory.mktemp("half")
    scene = load_gltf(REPO / "data" / "sample_room.glb")
    grid = GridSpec.from_counts((-1.0, 1.0, -1.0), (1.0, 1.5, 1.0), (2, 1, 2))
    out = {}
    for dtype in ("float", "half"):
        out[dtype] = root / f"{dtype}.probes"
        bake(scene, grid, out[dtype], settings=BakeSettings(
            face_size=8, diffuse_size=4, bounces=0, store_incoming=True, dtype=dtype))
    return out


def test_half_maps_are_the_float_maps_rounded_to_half(pair):
    f, h = open_store(pair["float"]), open_store(pair["half"])
    check_store(h)  # servable: finite, shapes and levels as export and the service need
    for name in f.names:
        want = np.asarray(f[name])
        got = np.asarray(h[name])
        if name.startswith(("diffuse", "specular_", "incoming")):
            assert h.manifest.arrays[name].dtype == "<f2" and got.dtype == np.float16, name
            np.testing.assert_array_equal(got, np.clip(want, -HALF_MAX, HALF_MAX)
                                          .astype(np.float16), err_msg=name)
        else:
            assert h.manifest.arrays[name].dtype == f.manifest.arrays[name].dtype, name
            np.testing.assert_array_equal(got, want, err_msg=name)
    assert h.manifest.bake["settings"]["dtype"] == "half"


def test_half_stores_read_back_in_float32(pair):
    f, h = ProbeField(open_store(pair["float"])), ProbeField(open_store(pair["half"]))
    p = [[0.1, 1.2, -0.3]]
    for kind in ("diffuse", "specular", "incoming"):
        a, b = f.cube(f.weights(p), kind), h.cube(h.weights(p), kind)
        assert b.dtype == np.float32
        np.testing.assert_allclose(b, a, rtol=2.0**-10, atol=1e-6)


def test_the_estimate_states_both_sizes_and_half_never_overflows(pair):
    st = BakeSettings(face_size=16, diffuse_size=8)
    full, half = store_bytes(st, 16384, "float"), store_bytes(st, 16384, "half")
    maps = 16384 * 6 * 3 * (8 * 8 + sum((16 >> k) ** 2 for k in range(5)))
    assert full - half == maps * 2  # the maps shrink from 4 to 2 bytes, nothing else changes
    note = size_note(st, 16384)
    assert f"{full / 2**20:,.1f} MiB with float maps" in note
    assert f"--dtype half: {half / 2**20:,.1f} MiB" in note
    out = {"specular_0": np.array([1e6, -1e6, 3.0], np.float32), "sh": np.array([1e6])}
    fit_map_dtype(out, "half")
    assert out["specular_0"].dtype == np.float16 and np.isfinite(out["specular_0"]).all()
    assert out["specular_0"].tolist() == [HALF_MAX, -HALF_MAX, 3.0]
    assert out["sh"].tolist() == [1e6]
