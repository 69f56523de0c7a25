"""Tests of probegrid.jobs.samples: the analytic sky and the hand-written sample room, and that the
committed files in data/ are what the code generates."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from probegrid.core.layouts import direction_to_equirect, equirect_directions
from probegrid.core.lights import PointLight
from probegrid.jobs.samples import (
    LAMP_INTENSITY,
    LAMP_POSITION,
    PANEL_EMISSION,
    ROOM_MAX,
    ROOM_MIN,
    SUN_DIRECTION,
    SUN_RADIUS,
    WINDOW,
    sample_room_glb_bytes,
    sample_room_gltf,
    sample_sky,
)
from probegrid.raytrace import RayTracer
from probegrid.scene import load_gltf

DATA = Path(__file__).resolve().parents[1] / "data"


def _pixel_solid_angles(h: int, w: int) -> np.ndarray:
    """(H, 1) exact solid angle of each lat-long pixel row."""
    edges = np.pi * (0.5 - np.arange(h + 1) / h)  # latitude of row edges, top to bottom
    return ((np.sin(edges[:-1]) - np.sin(edges[1:])) * (2 * np.pi / w))[:, None]


def test_sky_shape_determinism_and_sun() -> None:
    sky = sample_sky(512)
    assert sky.shape == (256, 512, 3) and sky.dtype == np.float32
    assert np.all(np.isfinite(sky)) and np.all(sky > 0)
    np.testing.assert_array_equal(sky, sample_sky(512))
    # the sun's pixels are centred where SUN_DIRECTION lands in the project's equirect layout
    rows, cols = np.nonzero(sky[..., 0] > 100.0)
    weight = sky[rows, cols, 0]
    x, y = direction_to_equirect(np.asarray(SUN_DIRECTION), 256, 512)
    assert abs(np.average(cols, weights=weight) - x) < 0.25
    assert abs(np.average(rows, weights=weight) - y) < 0.25
    # the sun disc's irradiance at normal incidence ~ L_sun * pi * radius^2
    d = equirect_directions(256, 512)
    near = (d @ np.asarray(SUN_DIRECTION)) > math.cos(2 * SUN_RADIUS)
    omega = np.broadcast_to(_pixel_solid_angles(256, 512), near.shape)
    e_sun = float(np.sum((sky[..., 0] - 1.5)[near] * omega[near]))  # minus the sky around it
    assert e_sun == pytest.approx(1500.0 * math.pi * SUN_RADIUS**2, rel=0.1)
    # ground (below the horizon) is dimmer than the sky just above it, and darkest at the nadir
    assert sky[130, :, 2].mean() < sky[125, :, 2].mean()
    assert sky[-1, :, 0].mean() < sky[130, :, 0].mean()
    with pytest.raises(ValueError):
        sample_sky(511)


def test_room_glb_is_deterministic_and_small(tmp_path: Path) -> None:
    blob = sample_room_glb_bytes()
    assert blob == sample_room_glb_bytes()
    assert blob[:4] == b"glTF" and len(blob) < 300_000
    p = sample_room_gltf(tmp_path / "room.glb")
    assert p.read_bytes() == blob
    with pytest.raises(ValueError):
        sample_room_gltf(tmp_path / "room.gltf")


def test_room_loads_with_lights_and_materials(tmp_path: Path) -> None:
    s = load_gltf(sample_room_gltf(tmp_path / "room.glb"))
    assert s.n_triangles == 44  # 6 room quads + 4 window-wall quads + panel + 2 boxes (12 each)
    np.testing.assert_allclose(s.bounds, [ROOM_MIN, ROOM_MAX], atol=1e-6)
    (lamp,) = s.lights
    assert isinstance(lamp, PointLight)
    np.testing.assert_allclose(lamp.position, LAMP_POSITION, atol=1e-12)
    assert lamp.intensity == LAMP_INTENSITY and lamp.range == 8.0
    by_name = {m.name: m for m in s.materials}
    np.testing.assert_allclose(by_name["panel"].emissive, PANEL_EMISSION)
    np.testing.assert_allclose(by_name["red"].base_color, [0.8, 0.1, 0.1, 1.0], rtol=1e-7)
    np.testing.assert_allclose(by_name["green"].base_color, [0.1, 0.8, 0.1, 1.0], rtol=1e-7)
    floor = by_name["floor"].base_color_texture
    assert floor is not None and floor.shape == (16, 16, 4)
    # checker values decoded from sRGB 225 / 150
    np.testing.assert_allclose(np.unique(floor[..., 0]), [0.30498, 0.75294], atol=1e-4)

    rt = RayTracer.from_scene(s)
    centre = np.array([0.0, 1.6, 0.0])
    dirs = np.array(
        [
            [0.0, 0.0, 1.0],  # through the window's middle (y 1.6 in [1, 2.2])
            [0.0, 0.0, -1.0],  # back wall at z = -2
            [-1.0, 0.0, 0.0],  # red wall
            [1.0, 0.0, 0.0],  # green wall
            [0.0, 1.0, 0.0],  # emissive panel at y = 2.98
            [0.0, -0.4, 1.0],  # front wall under the sill (reaches z = 2 at y = 0.8 < 1)
        ]
    )
    h = rt.intersect(centre, dirs)
    assert h.prim_id[0] == -1
    assert np.all(h.prim_id[1:] >= 0) and not rt.backface(h.prim_id[1:], dirs[1:]).any()
    np.testing.assert_allclose(h.t[1:], [2.0, 2.0, 2.0, 1.38, 2.0], atol=1e-5)
    surf = s.surface_at(h.prim_id[1:], h.u[1:], h.v[1:])
    white, red, green = [0.8, 0.8, 0.8], [0.8, 0.1, 0.1], [0.1, 0.8, 0.1]
    np.testing.assert_allclose(surf.albedo[[0, 1, 2, 4]], [white, red, green, white], rtol=1e-6)
    np.testing.assert_allclose(surf.emission[3], PANEL_EMISSION)
    assert WINDOW[2] == 1.0
    # from outside, the room's walls are back faces
    out = rt.intersect([0.0, 1.5, -3.0], [0.0, 0.0, 1.0])
    assert out.prim_id >= 0 and rt.backface(out.prim_id, [0.0, 0.0, 1.0])


def test_committed_data_is_current() -> None:
    assert (DATA / "sample_room.glb").read_bytes() == sample_room_glb_bytes()
    hdr = DATA / "sample_sky.hdr"
    assert hdr.stat().st_size < 300_000
    import OpenImageIO as oiio  # tests may read files directly; the library uses imageio.py

    buf = oiio.ImageBuf(str(hdr))
    assert not buf.has_error
    pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)[..., :3]
    expect = sample_sky(512)
    assert pixels.shape == expect.shape
    # RGBE keeps 8 mantissa bits relative to the largest channel
    np.testing.assert_allclose(pixels, expect, rtol=0.025, atol=1e-3)
