"""Tests of probegrid.scene: glTF loading (real files and hand-made ones), materials, lights,
surface queries, builders, bad-scene errors and content hashing."""

from __future__ import annotations

import json
import math
import pickle
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from probegrid.core.color import srgb_to_linear
from probegrid.core.lights import DirectionalLight, PointLight, SpotLight
from probegrid.scene import (
    Material,
    Scene,
    SceneBuilder,
    SceneError,
    box_mesh,
    box_scene,
    load_gltf,
    quad_mesh,
    sample_texture,
)

# --------------------------------------------------------------------------------------------
# helpers: hand-written .gltf files


def _png(pixels: np.ndarray) -> bytes:
    h, w, _ = pixels.shape

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    raw = np.concatenate([np.zeros((h, 1), np.uint8), pixels.reshape(h, w * 3)], axis=1)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw.tobytes()))
        + chunk(b"IEND", b"")
    )


def _write_gltf(
    directory: Path,
    *,
    positions: np.ndarray | None = None,
    nodes: list | None = None,
    lights: list | None = None,
    material: dict | None = None,
    images: list | None = None,
    with_mesh: bool = True,
    write_bin: bool = True,
) -> Path:
    """A one-triangle .gltf with an external .bin, a material and optional lights/images."""
    pos = (
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        if positions is None
        else np.asarray(positions, np.float32)
    )
    uv = np.array([[0, 0], [1, 0], [0, 1]], np.float32)
    blob = pos.tobytes() + uv.tobytes()
    if write_bin:
        (directory / "mesh.bin").write_bytes(blob)
    header: dict = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": nodes if nodes is not None else [{"mesh": 0}],
        "buffers": [{"uri": "mesh.bin", "byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": pos.nbytes},
            {"buffer": 0, "byteOffset": pos.nbytes, "byteLength": uv.nbytes},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3"},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"},
        ],
        "materials": [material if material is not None else {"name": "m"}],
    }
    if with_mesh:
        header["meshes"] = [
            {"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "material": 0}]}
        ]
    else:
        for node in header["nodes"]:
            node.pop("mesh", None)
    if lights is not None:
        header["extensionsUsed"] = ["KHR_lights_punctual"]
        header["extensions"] = {"KHR_lights_punctual": {"lights": lights}}
    if images is not None:
        header["images"] = images
        header["textures"] = [{"source": i} for i in range(len(images))]
    path = directory / "scene.gltf"
    path.write_text(json.dumps(header))
    return path


def _one_line_error(excinfo: pytest.ExceptionInfo) -> str:
    msg = str(excinfo.value)
    assert msg and "\n" not in msg
    return msg


# --------------------------------------------------------------------------------------------
# real scenes


def test_cornell_box(real_data: Path) -> None:
    s = load_gltf(real_data / "gltf" / "CornellBox.glb")
    assert s.n_triangles == 36
    assert s.lights == ()
    lo, hi = s.bounds
    np.testing.assert_allclose(lo, [-556.0, 0.0, -559.2], atol=0.01)
    np.testing.assert_allclose(hi, [0.0, 548.8, 0.0], atol=0.01)
    by_name = {m.name: i for i, m in enumerate(s.materials)}
    red, green = by_name["cbox.red.002"], by_name["cbox.green.002"]
    light = by_name["Emitter_Light_temp"]
    np.testing.assert_array_equal(s.materials[red].base_color, [0.5, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(s.materials[green].base_color, [0.0, 0.5, 0.0, 1.0])
    np.testing.assert_allclose(s.materials[by_name["cbox.Material.002"]].base_color[:3], 0.4)
    # emissive = emissiveFactor (1, 1, 1) * KHR_materials_emissive_strength (100)
    np.testing.assert_array_equal(s.materials[light].emissive, [100.0, 100.0, 100.0])
    assert all(np.all(m.emissive == 0) for i, m in enumerate(s.materials) if i != light)
    assert all(m.double_sided for m in s.materials)
    # walls: red at x = -556 facing +X (into the box), green at x = 0 facing -X
    for mat, x, nx in ((red, -556.0, 1.0), (green, 0.0, -1.0)):
        tris = np.flatnonzero(s.material == mat)
        assert len(tris) == 2
        np.testing.assert_allclose(
            s.vertices[s.triangles[tris]][..., 0], x, atol=7.0
        )  # not quite planar-aligned
        np.testing.assert_allclose(s.triangle_normals[tris][:, 0], nx, atol=1e-3)
    # the light quad: 2 triangles just under the ceiling, facing down, emitting 100
    tris = np.flatnonzero(s.material == light)
    assert len(tris) == 2
    np.testing.assert_allclose(s.vertices[s.triangles[tris]][..., 1], 547.9135, atol=1e-3)
    np.testing.assert_allclose(s.triangle_normals[tris], [[0, -1, 0]] * 2, atol=1e-6)
    surf = s.surface_at(tris, [1 / 3, 1 / 3], [1 / 3, 1 / 3])
    np.testing.assert_allclose(surf.emission, 100.0)
    np.testing.assert_allclose(surf.albedo, 0.8, rtol=1e-6)


def test_cubes_point_light_and_transforms(real_data: Path) -> None:
    s = load_gltf(real_data / "gltf" / "Cubes.glb")
    assert s.n_triangles == 36
    assert len(s.lights) == 1
    (light,) = s.lights
    assert isinstance(light, PointLight)
    assert light.intensity == pytest.approx(79.57747201077999, rel=1e-15)
    assert light.intensity == pytest.approx(250.0 / math.pi, rel=1e-6)  # 1000 lm / (4 pi)
    np.testing.assert_allclose(
        light.position, [-0.5162290334701538, 3.7671890258789062, -0.8318405151367188]
    )
    assert light.color == (1.0, 1.0, 1.0)
    assert light.range is None
    # factors come from the JSON at full precision (trimesh keeps only 8 bits)
    np.testing.assert_array_equal(
        s.materials[0].base_color, [0.8000000715255737, 0.05650300532579422, 0.10698337852954865, 1]
    )
    # node transforms: each cube (corners at +-1) is centred on its node translation and
    # scaled uniformly, so its corners lie sqrt(3) * scale from the centre
    for mat, t, scale in (
        (0, [-0.7717686891555786, 2.4418985843658447, 2.4895193576812744], 1.1495295763015747),
        (1, [-2.5435538291931152, 1.0536036491394043, -1.5017304420471191], 1.1162621974945068),
        (2, [2.7712512016296387, -0.40817153453826904, 0.9074176549911499], 1.0954933166503906),
    ):
        v = s.vertices[np.unique(s.triangles[s.material == mat])]
        np.testing.assert_allclose(v.mean(axis=0), t, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(v - t, axis=1), math.sqrt(3) * scale, rtol=1e-6)
        # outward normals: every face normal points away from the cube's centre
        tris = np.flatnonzero(s.material == mat)
        centroids = s.vertices[s.triangles[tris]].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", s.triangle_normals[tris], centroids - t) > 0)


def test_hash_stable_across_loads(real_data: Path) -> None:
    a = load_gltf(real_data / "gltf" / "CornellBox.glb")
    b = load_gltf(real_data / "gltf" / "CornellBox.glb")
    c = load_gltf(real_data / "gltf" / "Cubes.glb")
    assert a.content_hash() == b.content_hash() != c.content_hash()
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert len(a.content_hash()) == 64
    assert pickle.loads(pickle.dumps(a)).content_hash() == a.content_hash()


# --------------------------------------------------------------------------------------------
# hand-made glTF: lights, textures, hierarchy, winding


def test_lights_from_json_with_hierarchy(tmp_path: Path) -> None:
    s = 1 / math.sqrt(2)
    nodes = [
        {"mesh": 0, "children": [1, 2, 3], "translation": [10.0, 0.0, 0.0]},
        # spot pointing down: rotation -90 deg about X maps -Z to -Y
        {
            "translation": [0, 3, 0],
            "rotation": [-s, 0, 0, s],
            "extensions": {"KHR_lights_punctual": {"light": 0}},
        },
        # directional from a column-major matrix: rotation +90 deg about Y maps -Z to -X
        {
            "matrix": [0, 0, -1, 0, 0, 1, 0, 0, 1, 0, 0, 0, 1, 2, 3, 1],
            "extensions": {"KHR_lights_punctual": {"light": 1}},
        },
        {"translation": [0, 0, -1], "extensions": {"KHR_lights_punctual": {"light": 2}}},
    ]
    lights = [
        {
            "type": "spot",
            "intensity": 12.0,
            "color": [1, 0.5, 0.25],
            "range": 7.5,
            "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.6},
        },
        {"type": "directional", "intensity": 3.0},
        {"type": "point"},
    ]
    scene = load_gltf(_write_gltf(tmp_path, nodes=nodes, lights=lights))
    spot, sun, point = scene.lights
    assert isinstance(spot, SpotLight)
    np.testing.assert_allclose(spot.position, [10, 3, 0], atol=1e-12)
    np.testing.assert_allclose(spot.direction, [0, -1, 0], atol=1e-12)
    assert spot.color == (1.0, 0.5, 0.25)
    assert (spot.intensity, spot.range) == (12.0, 7.5)
    assert (spot.inner_cone_angle, spot.outer_cone_angle) == (0.2, 0.6)
    assert isinstance(sun, DirectionalLight)
    np.testing.assert_allclose(sun.direction, [-1, 0, 0], atol=1e-12)
    assert sun.intensity == 3.0 and sun.color == (1.0, 1.0, 1.0)
    assert isinstance(point, PointLight)  # glTF defaults: intensity 1, white, no range
    np.testing.assert_allclose(point.position, [10, 0, -1])
    assert (point.intensity, point.color, point.range) == (1.0, (1.0, 1.0, 1.0), None)
    # the mesh node's translation moved the triangle
    np.testing.assert_allclose(scene.bounds, [[10, 0, 0], [11, 1, 0]])


def test_texture_srgb_uv_and_emissive(tmp_path: Path) -> None:
    pixels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [128, 128, 128]]], np.uint8)
    (tmp_path / "tex.png").write_bytes(_png(pixels))
    material = {
        "pbrMetallicRoughness": {
            "baseColorFactor": [0.5, 1, 1, 1],
            "baseColorTexture": {"index": 0},
        },
        "emissiveFactor": [1, 1, 1],
        "emissiveTexture": {"index": 0},
        "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4.0}},
    }
    scene = load_gltf(_write_gltf(tmp_path, material=material, images=[{"uri": "tex.png"}]))
    m = scene.materials[0]
    assert m.base_color_texture is not None and m.base_color_texture.shape == (2, 2, 4)
    assert m.emissive_texture is not None and m.emissive_texture.shape == (2, 2, 3)
    np.testing.assert_allclose(m.base_color_texture[1, 1, :3], srgb_to_linear(128 / 255), rtol=1e-6)
    np.testing.assert_array_equal(m.emissive, [4.0, 4.0, 4.0])
    # glTF UVs: vertex 1 has uv (1, 0) (right edge, top row); trimesh's v-flip is undone
    np.testing.assert_allclose(scene.uvs, [[0, 0], [1, 0], [0, 1]])
    # barycentric (u, v) maps to uv (u, v) here; (0.75, 0.25) = centre of texel (row 0, col 1)
    surf = scene.surface_at(np.array([0]), np.array([0.75]), np.array([0.25]))
    np.testing.assert_allclose(surf.albedo, [[0.0, 1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(surf.emission, [[0.0, 4.0, 0.0]], atol=1e-6)
    # uv (0.25, 0.75): texel (row 1, col 0) = blue
    surf = scene.surface_at(0, 0.25, 0.75)
    np.testing.assert_allclose(surf.albedo, [0.0, 0.0, 1.0], atol=1e-6)
    surf = scene.surface_at(0, 0.25, 0.25)  # texel (0, 0) = red, times baseColorFactor 0.5
    np.testing.assert_allclose(surf.albedo, [0.5, 0.0, 0.0], atol=1e-6)


def test_negative_determinant_rewinds(tmp_path: Path) -> None:
    nodes = [{"mesh": 0, "scale": [-1, 1, 1]}]
    scene = load_gltf(_write_gltf(tmp_path, nodes=nodes))
    np.testing.assert_allclose(scene.vertices[:, 0], [0, -1, 0])
    # the triangle faced +Z; mirrored in X it still faces +Z (glTF: winding flips with det < 0)
    np.testing.assert_allclose(scene.triangle_normals, [[0, 0, 1]])


# --------------------------------------------------------------------------------------------
# bad scenes


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SceneError) as e:
        load_gltf(tmp_path / "nope.glb")
    assert "not found" in _one_line_error(e)


def test_truncated_glb(tmp_path: Path, real_data: Path) -> None:
    data = (real_data / "gltf" / "Cubes.glb").read_bytes()
    for cut in (8, 100, len(data) // 2, len(data) - 1):
        p = tmp_path / f"cut{cut}.glb"
        p.write_bytes(data[:cut])
        with pytest.raises(SceneError) as e:
            load_gltf(p)
        _one_line_error(e)


def test_garbage_files(tmp_path: Path) -> None:
    p = tmp_path / "garbage.glb"
    p.write_bytes(b"\x13\x37" * 500)
    with pytest.raises(SceneError) as e:
        load_gltf(p)
    assert "binary glTF" in _one_line_error(e)
    q = tmp_path / "garbage.gltf"
    q.write_text("{ not json")
    with pytest.raises(SceneError):
        load_gltf(q)
    r = tmp_path / "scene.obj"
    r.write_text("v 0 0 0")
    with pytest.raises(SceneError):
        load_gltf(r)


def test_missing_buffer_and_textures(tmp_path: Path) -> None:
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, write_bin=False))
    assert "mesh.bin" in _one_line_error(e)
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, material=material, images=[{"uri": "missing.png"}]))
    assert "missing.png" in _one_line_error(e)
    (tmp_path / "bad.png").write_bytes(b"definitely not a png" * 10)
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, material=material, images=[{"uri": "bad.png"}]))
    assert "bad.png" in _one_line_error(e)
    # a truncated PNG: valid header, cut image data
    (tmp_path / "cut.png").write_bytes(_png(np.zeros((64, 64, 3), np.uint8) + 7)[:60])
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, material=material, images=[{"uri": "cut.png"}]))
    _one_line_error(e)


def test_nan_vertices_and_empty_scene(tmp_path: Path) -> None:
    pos = np.array([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]])
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, positions=pos))
    assert "NaN" in _one_line_error(e)
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, with_mesh=False))
    assert "no triangles" in _one_line_error(e)
    with pytest.raises(SceneError):
        Scene.from_arrays(np.array([[0, 0, 0], [1, np.inf, 0], [0, 1, 0]]), [[0, 1, 2]])
    with pytest.raises(SceneError):
        Scene.from_arrays(np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(SceneError):
        Scene.from_arrays(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(SceneError):
        SceneBuilder().build()


def test_missing_texcoord_set_rejected(tmp_path: Path) -> None:
    (tmp_path / "t.png").write_bytes(_png(np.zeros((2, 2, 3), np.uint8)))
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0, "texCoord": 1}}}
    with pytest.raises(SceneError) as e:
        load_gltf(_write_gltf(tmp_path, material=material, images=[{"uri": "t.png"}]))
    assert "TEXCOORD_1" in _one_line_error(e)


def test_unsupported_required_extension_rejected_with_the_option(tmp_path: Path) -> None:
    path = _write_gltf(tmp_path)
    header = json.loads(path.read_text())
    header["extensionsRequired"] = ["KHR_lights_punctual", "KHR_materials_sheen"]
    header["materials"][0]["extensions"] = {"KHR_materials_sheen": {"sheenColorFactor": [1, 1,
                                                                                          1]}}
    path.write_text(json.dumps(header))
    with pytest.raises(SceneError) as e:
        load_gltf(path)
    msg = _one_line_error(e)
    assert "KHR_materials_sheen" in msg and "--ignore-extension KHR_materials_sheen" in msg
    scene = load_gltf(path, ignore_extensions=["KHR_materials_sheen"])
    assert "KHR_materials_sheen" in scene.unhonoured
    assert load_gltf(path, ignore_extensions=["*"]).unhonoured == scene.unhonoured


def test_from_arrays_rejects_bad_triangles() -> None:
    v = np.zeros((4, 3))
    with pytest.raises(SceneError, match="shape"):
        Scene.from_arrays(v, [[0, 1, 2, 3]])
    with pytest.raises(SceneError, match="integer"):
        Scene.from_arrays(v, [[0.0, 1.0, 2.0]])
    with pytest.raises(SceneError, match="no triangles"):
        Scene.from_arrays(v, [])


# --------------------------------------------------------------------------------------------
# building scenes, surfaces, textures


def test_box_scene_is_closed_and_inward() -> None:
    lo, hi = np.array([-1.0, 0.0, -2.0]), np.array([1.0, 3.0, 2.0])
    s = box_scene(lo, hi, albedo=0.5, emission=(1.0, 2.0, 3.0))
    assert s.n_triangles == 12
    d = hi - lo
    assert s.triangle_areas.sum() == pytest.approx(2 * (d[0] * d[1] + d[1] * d[2] + d[0] * d[2]))
    centroids = s.vertices[s.triangles].mean(axis=1)
    inward = np.einsum("ij,ij->i", s.triangle_normals, 0.5 * (lo + hi) - centroids)
    assert np.all(inward > 0)
    # every face normal is an axis direction, each of the 6 used by 2 triangles
    axes, counts = np.unique(np.round(s.triangle_normals, 12), axis=0, return_counts=True)
    assert len(axes) == 6 and np.all(counts == 2)
    surf = s.surface_at(np.arange(12), np.full(12, 0.2), np.full(12, 0.3))
    np.testing.assert_array_equal(surf.albedo, 0.5)
    np.testing.assert_array_equal(surf.emission, np.tile([1.0, 2.0, 3.0], (12, 1)))
    out = box_scene(lo, hi, albedo=0.5, inward=False)
    outward = np.einsum("ij,ij->i", out.triangle_normals, 0.5 * (lo + hi) - centroids)
    assert np.all(outward < 0)
    v, t, uv = box_mesh(lo, hi)
    assert v.shape == (24, 3) and t.shape == (12, 3) and uv.shape == (24, 2)


def test_surface_at_positions_and_shapes() -> None:
    v, t, uv = quad_mesh((1.0, 2.0, 3.0), (2.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    s = Scene.from_arrays(v, t, uvs=uv)
    np.testing.assert_allclose(s.triangle_normals, [[0, 1, 0], [0, 1, 0]])
    pid = np.array([[0, 1, 0], [1, 1, 0]])
    u = np.full((2, 3), 0.25)
    w = np.array([0.1, 0.2, 0.3])  # broadcast along the last axis
    surf = s.surface_at(pid, u, w)
    assert surf.position.shape == surf.normal.shape == surf.albedo.shape == (2, 3, 3)
    tri = s.vertices[s.triangles[pid]]
    expect = (
        (1 - u - w)[..., None] * tri[..., 0, :]
        + u[..., None] * tri[..., 1, :]
        + w[..., None] * tri[..., 2, :]
    )
    np.testing.assert_allclose(surf.position, expect)
    np.testing.assert_allclose(surf.position[..., 1], 2.0)
    with pytest.raises(ValueError):
        s.surface_at(-1, 0.0, 0.0)
    with pytest.raises(ValueError):
        s.surface_at(2, 0.0, 0.0)


def test_vertex_colors_multiply_albedo() -> None:
    v, t, _ = quad_mesh((0, 0, 0), (1, 0, 0), (0, 1, 0))
    colors = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    s = Scene.from_arrays(v, t, colors=colors, materials=[Material.diffuse((0.5, 0.5, 0.5))])
    surf = s.surface_at(0, 1 / 3, 1 / 3)  # centroid of vertices 0, 1, 2
    np.testing.assert_allclose(surf.albedo, [0.5 / 3] * 3)


def test_sample_texture_bilinear_and_wrap() -> None:
    tex = np.arange(8, dtype=np.float32).reshape(2, 2, 2)  # texels (r, c) = [4r + 2c, 4r + 2c + 1]
    centres = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    np.testing.assert_allclose(sample_texture(tex, centres), tex.reshape(4, 2)[[0, 1, 2, 3]])
    # the corner (0, 0) sits between all four texels under REPEAT, on texel (0, 0) under clamp
    np.testing.assert_allclose(sample_texture(tex, [0.0, 0.0]), tex.reshape(4, 2).mean(axis=0))
    np.testing.assert_allclose(sample_texture(tex, [0.0, 0.0], wrap=("clamp", "clamp")), tex[0, 0])
    np.testing.assert_allclose(
        sample_texture(tex, [0.0, 0.0], wrap=("mirror", "mirror")), tex[0, 0]
    )
    np.testing.assert_allclose(sample_texture(tex, [[3.25, -0.75]]), tex[[0], [0]])  # repeat
    np.testing.assert_allclose(sample_texture(tex, [0.5, 0.25]), 0.5 * (tex[0, 0] + tex[0, 1]))
    with pytest.raises(ValueError, match="repeat, clamp, mirror"):
        sample_texture(tex, [0.5, 0.5], wrap=("wrap", "repeat"))  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        sample_texture(tex, [np.nan, 0.5])


def test_srgb_to_linear_reference_values() -> None:
    np.testing.assert_allclose(
        srgb_to_linear([0.0, 0.04045, 0.5, 1.0]), [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-6
    )


def test_material_validation() -> None:
    m = Material(base_color=(0.2, 0.3, 0.4))
    np.testing.assert_array_equal(m.base_color, [0.2, 0.3, 0.4, 1.0])
    with pytest.raises(ValueError):
        Material(base_color=(np.nan, 0, 0))
    with pytest.raises(ValueError):
        Material(emissive=(-1, 0, 0))
    with pytest.raises(ValueError, match="repeat, clamp, mirror"):
        Material(base_color_wrap=("repeat", "bogus"))  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        Material(base_color_texture=np.zeros((2, 2, 3)))


def test_content_hash_sensitivity() -> None:
    base = box_scene(
        (0, 0, 0), (1, 1, 1), albedo=0.5, lights=[PointLight((0.5, 0.5, 0.5), (1, 1, 1), 2.0)]
    )
    same = box_scene(
        (0, 0, 0), (1, 1, 1), albedo=0.5, lights=[PointLight((0.5, 0.5, 0.5), (1, 1, 1), 2.0)]
    )
    assert base.content_hash() == same.content_hash()
    variants = [
        box_scene((0, 0, 0), (1, 1, 1 + 1e-12), albedo=0.5, lights=base.lights),
        box_scene((0, 0, 0), (1, 1, 1), albedo=0.5000001, lights=base.lights),
        box_scene((0, 0, 0), (1, 1, 1), albedo=0.5, emission=1e-9, lights=base.lights),
        box_scene(
            (0, 0, 0), (1, 1, 1), albedo=0.5, lights=[PointLight((0.5, 0.5, 0.5), (1, 1, 1), 2.5)]
        ),
        box_scene((0, 0, 0), (1, 1, 1), albedo=0.5, double_sided=True, lights=base.lights),
        box_scene((0, 0, 0), (1, 1, 1), albedo=0.5),
    ]
    hashes = {v.content_hash() for v in variants}
    assert len(hashes) == len(variants) and base.content_hash() not in hashes
    # pinned: the encoding is part of the store format (a stored bake names its scene by it)
    assert base.content_hash() == PINNED_BOX_HASH


PINNED_BOX_HASH = "389ee4edf3cfd84b324afc288ed70f11f2c2981e6ec5454ea87bae77e53c8b2a"


@pytest.mark.parametrize("change", [
    {"asset": "2.0"}, {"buffers": "x"}, {"materials": [5]}, {"extensionsRequired": 5},
    {"nodes": [{"mesh": 0, "children": [1]}, {"children": [0]}]},  # a cycle
])
def test_json_of_the_wrong_shape_is_a_scene_error(tmp_path: Path, change: dict) -> None:
    path = _write_gltf(tmp_path)
    header = json.loads(path.read_text())
    header.update(change)
    path.write_text(json.dumps(header))
    with pytest.raises(SceneError) as e:
        load_gltf(path)
    assert path.name in _one_line_error(e)


def test_an_interrupt_during_trimesh_loading_is_not_swallowed(tmp_path: Path, monkeypatch,
                                                              real_data: Path) -> None:
    """trimesh's loaders catch BaseException: a Ctrl-C that lands inside them must still stop
    the program once loading returns."""
    import os
    import signal

    import trimesh

    real = trimesh.load_scene

    def interrupted_load(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C, in the middle of trimesh's work
            signal.getsignal(signal.SIGINT)(signal.SIGINT, None)  # run the handler now
        except BaseException:  # noqa: BLE001, S110 -- what trimesh does
            pass
        return real(*args, **kwargs)

    monkeypatch.setattr(trimesh, "load_scene", interrupted_load)
    # Python's own Ctrl-C handler, whatever this process inherited: started in the background
    # (``&``, nohup, many CI runners) SIGINT begins as SIG_IGN and no KeyboardInterrupt exists
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            load_gltf(real_data / "gltf" / "Cubes.glb")
    finally:
        signal.signal(signal.SIGINT, previous)


# ---------------------------------------------------------------------------- confined to the folder
_TEXTURED = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}


def _reads(monkeypatch) -> list[str]:
    """Every file read through Path.read_bytes from now on."""
    seen: list[str] = []
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: seen.append(str(self)) or real(self))
    return seen


@pytest.mark.parametrize("uri", ["../secret.png", "%2E%2E/secret.png", "{abs}", "file://{abs}",
                                 "link.png"])
def test_uris_outside_the_scene_folder_are_refused_before_any_read(tmp_path, monkeypatch, uri):
    folder = tmp_path / "scene"
    folder.mkdir()
    secret = tmp_path / "secret.png"
    secret.write_bytes(_png(np.zeros((2, 2, 3), np.uint8)) + b"\0" * 12345)
    (folder / "link.png").symlink_to(secret)
    path = _write_gltf(folder, material=_TEXTURED,
                       images=[{"uri": uri.format(abs=secret)}])
    seen = _reads(monkeypatch)
    with pytest.raises(SceneError) as info:
        load_gltf(path)
    msg = _one_line_error(info)
    assert "--allow-path" in msg and str(secret.stat().st_size) not in msg
    assert str(secret) not in seen and str(folder / "link.png") not in seen


def test_a_buffer_outside_the_folder_is_refused_without_its_size(tmp_path):
    folder = tmp_path / "scene"
    folder.mkdir()
    (tmp_path / "big.bin").write_bytes(b"\0" * 4321)
    path = _write_gltf(folder)
    header = json.loads(path.read_text())
    header["buffers"][0].update(uri="../big.bin", byteLength=99999)
    path.write_text(json.dumps(header))
    with pytest.raises(SceneError, match="outside the scene's folder") as info:
        load_gltf(path)
    assert "4321" not in _one_line_error(info)


def test_allow_paths_lets_a_shared_texture_folder_in(tmp_path):
    folder = tmp_path / "scene"
    (tmp_path / "textures").mkdir()
    folder.mkdir()
    pixels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [128, 128, 128]]], np.uint8)
    (tmp_path / "textures" / "tex.png").write_bytes(_png(pixels))
    path = _write_gltf(folder, material=_TEXTURED, images=[{"uri": "../textures/tex.png"}])
    with pytest.raises(SceneError, match="name it with --allow-path DIR"):
        load_gltf(path)
    scene = load_gltf(path, allow_paths=[tmp_path / "textures"])
    tex = scene.materials[0].base_color_texture
    assert tex is not None and tex.shape == (2, 2, 4)
    np.testing.assert_allclose(tex[0, 0, :3], [1, 0, 0])
