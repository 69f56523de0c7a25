"""The glTF features that change light transport, with physics: cut-outs (alphaMode MASK),
partial coverage (BLEND), thin transmission, texture coordinates (texCoord sets and
KHR_texture_transform), emissive strength; and the geometry encodings (KHR_mesh_quantization,
sparse accessors, EXT_meshopt_compression, KHR_draco_mesh_compression) that must load as the
plain geometry they encode. Every scene is built here, in code or as glTF JSON."""

from __future__ import annotations

import base64
import io
import json
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake.driver import BakeSettings, bake
from probegrid.core.cubemap import texel_solid_angles
from probegrid.core.grid import GridSpec
from probegrid.core.lights import DirectionalLight
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.raytrace.kernels import embree_rays
from probegrid.scene import (
    Material,
    Scene,
    SceneBuilder,
    SceneError,
    load_gltf,
    quad_mesh,
    sample_texture,
    texture_transform,
)

FAST = {"face_size": 16, "diffuse_size": 4, "moments_size": 4, "batch_size": 4}


def _holes(n: int = 64, seed: int = 3) -> np.ndarray:
    """An RGBA texture, white, whose alpha is 0 on exactly half of its texels (at random)."""
    tex = np.ones((n, n, 4), np.float32)
    alpha = np.zeros(n * n, np.float32)
    alpha[np.random.default_rng(seed).permutation(n * n)[: n * n // 2]] = 1.0
    tex[..., 3] = alpha.reshape(n, n)
    return tex


def _roof(material: Material, *, size: float = 40.0, tiles: float = 80.0) -> Scene:
    """A horizontal square roof at y = 1 facing down, its texture repeated ``tiles`` times."""
    v, t, uv = quad_mesh((-size / 2, 1.0, -size / 2), (0, 0, size), (size, 0, 0))
    return Scene.from_arrays(v, t, materials=[material], uvs=uv * tiles)


# --------------------------------------------------------------------------------------------
# the tracer: every kind of ray passes the same holes


def _vertical_rays(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    o = np.c_[rng.uniform(-10, 10, n), np.zeros(n), rng.uniform(-10, 10, n)]
    return o, np.tile([0.0, 1.0, 0.0], (n, 1))


def _every_kind_of_ray(tracer: RayTracer, o: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
    """Whether each ray gets through to y = 2: as a closest-hit ray (primary and gather rays),
    a shadow ray (float64 and as the bake's kernels write them) and a visibility segment."""
    org, dirs, far, ok = embree_rays(o, d, np.zeros(1), np.full(1, 2.0), tracer.centre)
    return {
        "closest hit": tracer.intersect(o, d).prim_id < 0,
        "shadow": ~tracer.occluded(o, d, 2.0),
        "shadow (Embree rays)": ~tracer.occluded_rays(EmbreeRays(org, dirs, far), ok),
        "segment": ~tracer.segments_occluded(o, o + 2 * d),
    }


def test_cutout_holes_pass_exactly_where_alpha_is_below_the_cutoff() -> None:
    """MASK: a ray passes exactly where the texture's (bilinear) alpha at its crossing point is
    below alphaCutoff -- for every kind of ray -- and so half of them through half holes."""
    tex = _holes()
    scene = _roof(Material(base_color_texture=tex, alpha_mode="MASK", alpha_cutoff=0.5))
    tracer = RayTracer.from_scene(scene)
    o, d = _vertical_rays(20000)
    # where each ray crosses the roof, in texture coordinates (quad_mesh's UVs (s, 1 - t),
    # s along +z and t along +x, times 80)
    uv = np.c_[(o[:, 2] + 20) / 40 * 80, (1 - (o[:, 0] + 20) / 40) * 80]
    alpha = sample_texture(tex, uv)[:, 3]
    expected = alpha < 0.5
    clear = np.abs(alpha - 0.5) > 1e-3  # (Embree's float32 hit points: rays on the edges)
    kinds = _every_kind_of_ray(tracer, o, d)
    for kind, passed in kinds.items():
        assert np.array_equal(passed[clear], expected[clear]), kind
        assert np.array_equal(passed, kinds["closest hit"]), kind
    assert clear.mean() > 0.99
    assert expected.mean() == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("material,passing", [
    (Material(base_color=(1, 1, 1, 0.3), alpha_mode="BLEND"), 0.7),
    (Material(transmission=0.6), 0.6),
    (Material(base_color=(1, 1, 1, 0.5), alpha_mode="BLEND", transmission=0.5), 0.75),
    (Material(base_color=(1, 1, 1, 0.3)), 0.0),  # OPAQUE ignores alpha
])
def test_partial_coverage_and_transmission_pass_their_share(material, passing) -> None:
    """BLEND: a ray stops with probability alpha; a thin transmitting pane passes
    ``transmission``; both: ``1 - alpha (1 - T)`` -- for every kind of ray (50k rays: 3 sigma
    is 0.7 %). The same ray decides the same way every time."""
    tracer = RayTracer.from_scene(_roof(material))
    o, d = _vertical_rays(50000)
    kinds = _every_kind_of_ray(tracer, o, d)
    for kind, passed in kinds.items():
        assert passed.mean() == pytest.approx(passing, abs=0.007), kind
    assert np.array_equal(tracer.intersect(o, d).prim_id, tracer.intersect(o, d).prim_id)


def test_a_pickled_tracer_and_scene_pass_the_same_rays() -> None:
    """A worker's tracer (pickled, rebuilt) and a scene pickled after its coverage was built
    decide every ray as the original does."""
    import pickle

    scene = _roof(Material(base_color=(1, 1, 1, 0.4), alpha_mode="BLEND", transmission=0.2))
    tracer = RayTracer.from_scene(scene)
    o, d = _vertical_rays(5000)
    again = pickle.loads(pickle.dumps(tracer))
    rebuilt = RayTracer.from_scene(pickle.loads(pickle.dumps(scene)))
    for other in (again, rebuilt):
        a, b = _every_kind_of_ray(tracer, o, d), _every_kind_of_ray(other, o, d)
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_transmittance_is_the_expected_share_along_a_segment() -> None:
    """Two panes of transmission 0.6 pass 0.36 of a segment through both (every ray, no
    draw); an opaque triangle on the way passes 0; a cut-out passes 0 or 1."""
    b = SceneBuilder()
    glass = b.add_material(Material(transmission=0.6))
    wall = b.add_material(Material.diffuse(0.5))
    fence = b.add_material(Material(base_color_texture=_holes(), alpha_mode="MASK"))
    b.add_quad((-1, 1, -1), (0, 0, 2), (2, 0, 0), material=glass)
    b.add_quad((-1, 2, -1), (0, 0, 2), (2, 0, 0), material=glass)
    b.add_quad((-1, 3, -1), (0, 0, 2), (2, 0, 0), material=wall)
    b.add_quad((-1, -1, -1), (0, 0, 2), (2, 0, 0), material=fence)
    tracer = RayTracer.from_scene(b.build())
    rng = np.random.default_rng(2)
    o = np.c_[rng.uniform(-0.9, 0.9, 3000), np.zeros(3000), rng.uniform(-0.9, 0.9, 3000)]
    up, down = np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])
    np.testing.assert_allclose(tracer.transmittance(o, up, 2.5), 0.36, rtol=1e-12)
    np.testing.assert_allclose(tracer.transmittance(o, up, 1.5), 0.6, rtol=1e-12)
    assert np.all(tracer.transmittance(o, up, 3.5) == 0.0)
    through = tracer.transmittance(o, down, 2.0)
    assert set(np.unique(through)) == {0.0, 1.0}
    assert np.array_equal(through == 1.0, ~tracer.occluded(o, down, 2.0))


@pytest.mark.slow
def test_a_probe_behind_glass_sees_the_sun_at_the_transmission_factor(tmp_path) -> None:
    """A probe under a clear (white: untinted) glass pane of transmission 0.6 gets exactly 0.6
    of the sun's irradiance (its view of a punctual light is the expected transmittance, not
    one draw)."""
    from probegrid.core.sh import K0

    def sh0(pane: Material, name: str) -> float:
        b = SceneBuilder()
        m = b.add_material(pane)
        v, t, _ = quad_mesh((-50, 2, -50), (100, 0, 0), (0, 0, 100))
        b.add_triangles(v, t, material=m)
        b.add_light(DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0), 3.0))
        grid = GridSpec.from_counts((0, 0.5, 0), (0, 0.5, 0), (1, 1, 1))
        st = BakeSettings(bounces=0, **FAST)
        return float(bake(b.build(), grid, tmp_path / f"{name}.probes",
                          settings=st).store["sh"][0, 0, 0])

    assert sh0(Material(base_color=(1, 1, 1, 1), transmission=0.6), "glass") == pytest.approx(
        0.6 * K0 * 3.0, rel=1e-5)


def test_a_ray_passes_several_cutouts_and_stops_at_an_opaque_floor_behind() -> None:
    """Two stacked cut-out layers with complementary holes stop every ray; the closest hit of
    a ray through the holes of one layer is on the next surface behind."""
    tex = _holes()
    inverse = tex.copy()
    inverse[..., 3] = 1 - tex[..., 3]
    b = SceneBuilder()
    m1 = b.add_material(Material(base_color_texture=tex, alpha_mode="MASK"))
    m2 = b.add_material(Material(base_color_texture=inverse, alpha_mode="MASK"))
    floor = b.add_material(Material.diffuse(0.5))
    b.add_quad((-1, 1, -1), (0, 0, 2), (2, 0, 0), material=m1)
    b.add_quad((-1, 1.5, -1), (0, 0, 2), (2, 0, 0), material=m2)
    b.add_quad((-1, 3, -1), (0, 0, 2), (2, 0, 0), material=floor)
    tracer = RayTracer.from_scene(b.build())
    rng = np.random.default_rng(4)
    o = np.c_[rng.uniform(-0.9, 0.9, 5000), np.zeros(5000), rng.uniform(-0.9, 0.9, 5000)]
    d = np.tile([0.0, 1.0, 0.0], (5000, 1))
    hits = tracer.intersect(o, d)
    assert set(np.unique(hits.t).round(6)) <= {1.0, 1.5}  # every ray stops at a layer
    assert tracer.occluded(o, d, 2.9).all()


# --------------------------------------------------------------------------------------------
# bakes: the sun through a cut-out roof and through a glass pane


def _sunlit_floor(roof: Material | None) -> Scene:
    """A floor (albedo 0.5) under a sun straight above, under a black roof of ``roof``'s
    coverage (None: no roof)."""
    b = SceneBuilder()
    floor = b.add_material(Material.diffuse(0.5))
    b.add_quad((-50, 0, 50), (100, 0, 0), (0, 0, -100), material=floor)  # faces +Y
    if roof is not None:
        m = b.add_material(roof)
        v, t, uv = quad_mesh((-50, 2, -50), (100, 0, 0), (0, 0, 100))  # faces -Y
        b.add_triangles(v, t, material=m, uvs=uv * 39.0625)  # 1 cm texels of _holes(256)
    b.add_light(DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0), 3.0))
    return b.build()


def _floor_light(tmp_path: Path, name: str, scene: Scene) -> float:
    """The light a probe 0.5 above the floor receives from below (the -Y face of its incoming
    cube, integrated over solid angle)."""
    grid = GridSpec.from_counts((0, 0.5, 0), (0, 0.5, 0), (1, 1, 1))
    st = BakeSettings(bounces=0, samples=8, store_incoming=True, direct=False, **FAST)
    s = bake(scene, grid, tmp_path / f"{name}.probes", settings=st).store
    down = np.asarray(s["incoming"][0])[3, ..., 0].astype(np.float64)
    return float(np.sum(down * texel_solid_angles(16)[3]))


@pytest.mark.slow
@pytest.mark.parametrize("roof,passing", [
    (Material(base_color=(0, 0, 0, 1), base_color_texture=_holes(256), alpha_mode="MASK"),
     0.5),
    (Material(base_color=(1, 1, 1, 1), transmission=0.6), 0.6),  # clear: untinted
    (Material(base_color=(0, 0, 0, 0.25), alpha_mode="BLEND"), 0.75),
], ids=["cutout", "glass", "blend"])
def test_the_sun_reaches_the_floor_through_holes_and_glass(tmp_path, roof, passing) -> None:
    """The floor under a roof with 50 % holes gets 50 % of the sun (its shadow rays pass the
    holes), under a glass pane of transmission 0.6 60 %, under a 25 % covering BLEND roof
    75 %: what a probe sees of the floor, against the same bake without a roof (2048 rays:
    3 sigma is 3 %)."""
    open_sky = _floor_light(tmp_path, "open", _sunlit_floor(None))
    assert open_sky > 0
    covered = _floor_light(tmp_path, "roof", _sunlit_floor(roof))
    assert covered / open_sky == pytest.approx(passing, abs=0.03)


def _lit_ceiling(roof: Material | None) -> Scene:
    """A floor (albedo 0.5) lit only by what it gathers: a white ceiling at y = 4 lit by a spot
    light at y = 3 that shines up (it reaches neither the floor nor the roof), seen through a
    black roof at y = 2 of ``roof``'s coverage (None: no roof)."""
    from probegrid.core.lights import SpotLight

    b = SceneBuilder()
    floor = b.add_material(Material.diffuse(0.5))
    ceiling = b.add_material(Material.diffuse(0.8))
    b.add_quad((-50, 0, 50), (100, 0, 0), (0, 0, -100), material=floor)  # faces +Y
    b.add_quad((-50, 4, -50), (100, 0, 0), (0, 0, 100), material=ceiling)  # faces -Y
    if roof is not None:
        m = b.add_material(roof)
        v, t, uv = quad_mesh((-50, 2, -50), (100, 0, 0), (0, 0, 100))
        b.add_triangles(v, t, material=m, uvs=uv * 39.0625)
    b.add_light(SpotLight((0.0, 3.0, 0.0), (0.0, 1.0, 0.0), (1.0, 1.0, 1.0), 50.0,
                          outer_cone_angle=1.5))
    return b.build()


@pytest.mark.slow
def test_gather_rays_bring_back_light_through_the_holes(tmp_path) -> None:
    """The floor under a roof with 50 % holes gathers 50 % of the light of a lit ceiling above
    the roof (its gather rays pass the holes): what a probe sees of the floor after one
    bounce, against the same bake without a roof (32k gather rays: 3 sigma is about 2 %)."""
    def floor_light(name: str, scene: Scene) -> float:
        grid = GridSpec.from_counts((0, 0.5, 0), (0, 0.5, 0), (1, 1, 1))
        st = BakeSettings(bounces=1, samples=8, gather_samples=16, gather_depth=1,
                          store_incoming=True, direct=False, **FAST)
        s = bake(scene, grid, tmp_path / f"{name}.probes", settings=st).store
        down = np.asarray(s["incoming"][0])[3, ..., 0].astype(np.float64)
        return float(np.sum(down * texel_solid_angles(16)[3]))

    open_roof = floor_light("open", _lit_ceiling(None))
    assert open_roof > 0
    holes = Material(base_color=(0, 0, 0, 1), base_color_texture=_holes(256), alpha_mode="MASK")
    assert floor_light("roof", _lit_ceiling(holes)) / open_roof == pytest.approx(0.5, abs=0.03)


# --------------------------------------------------------------------------------------------
# glTF files: materials and texture coordinates


def _png_bytes(pixels: np.ndarray, fmt: str = "PNG") -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt, **({"lossless": True} if fmt == "WEBP" else {}))
    return buf.getvalue()


def _data_uri(data: bytes, mime: str = "application/octet-stream") -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode()}"


def _quad_document(*, material: dict | None = None, images: list | None = None,
                   textures: list | None = None, uv1: np.ndarray | None = None,
                   size: float = 4.0) -> dict:
    """A .gltf document: one square floor quad (y = 0, facing +Y, x and z in [-size/2,
    size/2]) with TEXCOORD_0 (u along +x, v along +z, each 0 to 1), an optional TEXCOORD_1,
    one material, its images and textures; everything in one embedded buffer."""
    h = size / 2
    pos = np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    idx = np.array([0, 2, 1, 0, 3, 2], np.uint32)
    parts = [pos.tobytes(), uv.tobytes(), idx.tobytes()]
    attrs = {"POSITION": 0, "TEXCOORD_0": 1}
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
         "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": 2, "componentType": 5125, "count": 6, "type": "SCALAR"},
    ]
    if uv1 is not None:
        parts.append(np.asarray(uv1, np.float32).tobytes())
        accessors.append({"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC2"})
        attrs["TEXCOORD_1"] = 3
    views, offset = [], 0
    for p in parts:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(p)})
        offset += len(p)
    doc: dict = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attrs, "indices": 2, "material": 0}]}],
        "materials": [material or {"name": "floor"}],
        "buffers": [{"byteLength": offset, "uri": _data_uri(b"".join(parts))}],
        "bufferViews": views, "accessors": accessors,
    }
    if images is not None:
        doc["images"] = images
        doc["textures"] = textures if textures is not None else [
            {"source": i} for i in range(len(images))]
    return doc


def _write(tmp_path: Path, doc: dict, name: str = "scene.gltf") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def _halves() -> np.ndarray:
    """An 8x8 sRGB texture: red on its left half (u < 0.5), green on its right half."""
    px = np.zeros((8, 8, 3), np.uint8)
    px[:, :4, 0] = 255
    px[:, 4:, 1] = 255
    return px


def _colour_at(scene: Scene, x: float, z: float) -> np.ndarray:
    """The albedo of the floor at (x, 0, z) (a vertical ray's hit)."""
    hit = RayTracer.from_scene(scene).intersect([x, 1.0, z], [0.0, -1.0, 0.0])
    return scene.surface_at(hit.prim_id, hit.u, hit.v).albedo


@pytest.mark.parametrize("transform,left", [
    (None, "red"),
    ({"offset": [0.5, 0.0]}, "green"),              # shifted by half the image
    ({"scale": [-1.0, 1.0], "offset": [1.0, 0.0]}, "green"),  # mirrored
    ({"rotation": np.pi, "offset": [1.0, 1.0]}, "green"),     # turned half a turn
])
def test_a_transformed_texture_lands_where_the_transform_puts_it(tmp_path, transform,
                                                                 left) -> None:
    info: dict = {"index": 0}
    if transform is not None:
        info["extensions"] = {"KHR_texture_transform": transform}
    doc = _quad_document(material={"pbrMetallicRoughness": {"baseColorTexture": info}},
                         images=[{"uri": _data_uri(_png_bytes(_halves()), "image/png")}])
    if transform is not None:
        doc["extensionsUsed"] = doc["extensionsRequired"] = ["KHR_texture_transform"]
    scene = load_gltf(_write(tmp_path, doc))
    red, green = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    on_left, on_right = (red, green) if left == "red" else (green, red)
    np.testing.assert_allclose(_colour_at(scene, -1.0, 0.3), on_left, atol=1e-6)
    np.testing.assert_allclose(_colour_at(scene, 1.0, -0.3), on_right, atol=1e-6)


@pytest.mark.slow
def test_a_probe_sees_the_transformed_colour_on_its_side(tmp_path) -> None:
    """A probe low over the left half of a floor lit by a sun sees red there, and green once
    the texture is shifted by half its width (KHR_texture_transform offset)."""
    def seen(transform: dict | None, name: str) -> np.ndarray:
        info: dict = {"index": 0}
        if transform is not None:
            info["extensions"] = {"KHR_texture_transform": transform}
        doc = _quad_document(material={"pbrMetallicRoughness": {"baseColorTexture": info},
                                       "doubleSided": True},
                             images=[{"uri": _data_uri(_png_bytes(_halves()), "image/png")}],
                             size=40.0)
        # a sun straight down: a directional light's -Z turned to -Y
        doc["nodes"].append({"rotation": [-0.5**0.5, 0.0, 0.0, 0.5**0.5],
                             "extensions": {"KHR_lights_punctual": {"light": 0}}})
        doc["scenes"][0]["nodes"].append(1)
        doc["extensions"] = {"KHR_lights_punctual": {"lights": [
            {"type": "directional", "intensity": 2.0}]}}
        doc["extensionsUsed"] = ["KHR_lights_punctual", "KHR_texture_transform"]
        scene = load_gltf(_write(tmp_path, doc, f"{name}.gltf"))
        grid = GridSpec.from_counts((-10, 0.3, 0), (-10, 0.3, 0), (1, 1, 1))
        st = BakeSettings(bounces=0, store_incoming=True, **FAST)
        s = bake(scene, grid, tmp_path / f"{name}.probes", settings=st).store
        down = np.asarray(s["incoming"][0])[3].astype(np.float64)
        return np.einsum("ijc,ij->c", down, texel_solid_angles(16)[3])

    plain, shifted = seen(None, "plain"), seen({"offset": [0.5, 0.0]}, "shifted")
    assert plain[0] > 20 * plain[1]      # red below
    assert shifted[1] > 20 * shifted[0]  # green below
    assert plain[0] == pytest.approx(shifted[1], rel=1e-3)


def test_each_texture_reads_its_own_texcoord_set(tmp_path) -> None:
    """baseColorTexture with texCoord 1 reads TEXCOORD_1 (here the mirror image of TEXCOORD_0);
    KHR_texture_transform's texCoord overrides the textureInfo's."""
    uv1 = np.array([[1, 0], [0, 0], [0, 1], [1, 1]], np.float32)
    image = [{"uri": _data_uri(_png_bytes(_halves()), "image/png")}]
    red, green = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    for info, left in (({"index": 0, "texCoord": 1}, green),
                       ({"index": 0, "texCoord": 1,
                         "extensions": {"KHR_texture_transform": {"texCoord": 0}}}, red)):
        doc = _quad_document(material={"pbrMetallicRoughness": {"baseColorTexture": info}},
                             images=image, uv1=uv1)
        scene = load_gltf(_write(tmp_path, doc))
        np.testing.assert_allclose(_colour_at(scene, -1.0, 0.0), left, atol=1e-6)


def test_emissive_texture_strength_and_transform(tmp_path) -> None:
    """Emission = emissiveFactor x emissiveStrength x emissiveTexture (transformed)."""
    material = {"emissiveFactor": [1.0, 0.5, 1.0],
                "emissiveTexture": {"index": 0, "extensions": {
                    "KHR_texture_transform": {"offset": [0.5, 0.0]}}},
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 40.0}}}
    doc = _quad_document(material=material,
                         images=[{"uri": _data_uri(_png_bytes(_halves()), "image/png")}])
    scene = load_gltf(_write(tmp_path, doc))
    hit = RayTracer.from_scene(scene).intersect([-1.0, 1.0, 0.0], [0.0, -1.0, 0.0])
    np.testing.assert_allclose(scene.surface_at(hit.prim_id, hit.u, hit.v).emission,
                               [0.0, 20.0, 0.0], atol=1e-5)


def test_alpha_modes_and_transmission_load(tmp_path) -> None:
    tex = np.zeros((4, 4, 4), np.uint8)
    tex[..., 3] = 255
    tex[:, :2, 3] = 0  # transparent left half
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(tex, "RGBA").save(buf, format="PNG")
    material = {"alphaMode": "MASK", "alphaCutoff": 0.3,
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}},
                "extensions": {"KHR_materials_transmission": {"transmissionFactor": 0.25}}}
    doc = _quad_document(material=material,
                         images=[{"uri": _data_uri(buf.getvalue(), "image/png")}])
    doc["extensionsUsed"] = ["KHR_materials_transmission"]
    scene = load_gltf(_write(tmp_path, doc))
    m = scene.materials[0]
    assert (m.alpha_mode, m.alpha_cutoff, m.transmission) == ("MASK", 0.3, 0.25)
    cov = scene.coverage
    assert cov is not None and cov.cutout.all()
    tracer = RayTracer.from_scene(scene)
    hits = tracer.intersect([[-1.5, 1, 0], [1.5, 1, 0]], [[0, -1.0, 0]] * 2)
    assert hits.prim_id[0] == -1  # through the hole
    p = cov.stop_probability(np.array([0]), np.array([0.2]), np.array([0.2]))
    assert p[0] in (0.0, 0.75)


def test_a_reduced_cutout_keeps_the_share_of_rays_its_holes_pass(tmp_path) -> None:
    """A 64x64 MASK texture of fine 50 % holes (alpha 0.6 beside 0.2, cutoff 0.5) read at a
    16-texel limit: every reduced texel's alpha averages to 0.4, which a re-threshold would
    make all holes; the loader keeps the coverage (half the rays stop) as stochastic BLEND."""
    from PIL import Image

    from probegrid.scene.texels import TextureLimits

    tex = np.full((64, 64, 4), 255, np.uint8)
    tex[..., 3] = np.where((np.indices((64, 64)).sum(0) % 2) == 0, 153, 51)  # 0.6 / 0.2
    buf = io.BytesIO()
    Image.fromarray(tex, "RGBA").save(buf, format="PNG")
    material = {"alphaMode": "MASK", "alphaCutoff": 0.5,
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    path = _write(tmp_path, _quad_document(
        material=material, images=[{"uri": _data_uri(buf.getvalue(), "image/png")}]))
    full = load_gltf(path)
    reduced = load_gltf(path, textures=TextureLimits(max_size=16))
    assert full.materials[0].alpha_mode == "MASK"
    assert reduced.materials[0].alpha_mode == "BLEND"
    assert reduced.materials[0].base_color_texture.shape[:2] == (16, 16)
    o, d = _vertical_rays(20000)
    o, d = o * 0.19 + [0.0, 1.0, 0.0], -d  # (down onto the 4 m quad, from 1 m above)
    for scene in (full, reduced):
        stopped = RayTracer.from_scene(scene).intersect(o, d).prim_id >= 0
        assert abs(stopped.mean() - 0.5) < 0.02, stopped.mean()


def test_webp_and_basisu_textures(tmp_path) -> None:
    """EXT_texture_webp is decoded (Pillow); KHR_texture_basisu reads the fallback image its
    texture names; one without a fallback is refused, naming the option that bakes it with the
    texture left out."""
    webp = {"uri": _data_uri(_png_bytes(_halves(), "WEBP"), "image/webp")}
    ktx2 = {"uri": _data_uri(b"\xabKTX 20\xbb\r\n\x1a\n", "image/ktx2")}
    png = {"uri": _data_uri(_png_bytes(_halves()[:, ::-1].copy()), "image/png")}
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    red, green = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    doc = _quad_document(material=material, images=[webp],
                         textures=[{"extensions": {"EXT_texture_webp": {"source": 0}}}])
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_texture_webp"]
    np.testing.assert_allclose(_colour_at(load_gltf(_write(tmp_path, doc)), -1.0, 0.0), red,
                               atol=1e-6)
    doc = _quad_document(material=material, images=[ktx2, png], textures=[
        {"source": 1, "extensions": {"KHR_texture_basisu": {"source": 0}}}])
    doc["extensionsUsed"] = ["KHR_texture_basisu"]
    np.testing.assert_allclose(_colour_at(load_gltf(_write(tmp_path, doc)), -1.0, 0.0), green,
                               atol=1e-6)
    doc["textures"] = [{"extensions": {"KHR_texture_basisu": {"source": 0}}}]
    with pytest.raises(SceneError) as e:
        load_gltf(_write(tmp_path, doc))
    assert "--ignore-extension KHR_texture_basisu" in str(e.value)
    scene = load_gltf(_write(tmp_path, doc), ignore_extensions=["KHR_texture_basisu"])
    assert scene.materials[0].base_color_texture is None


def test_unhonoured_features_are_named(tmp_path) -> None:
    material = {"pbrMetallicRoughness": {"metallicFactor": 1.0},
                "normalTexture": {"index": 0},
                "extensions": {"KHR_materials_sheen": {}, "KHR_materials_clearcoat": {}}}
    doc = _quad_document(material=material,
                         images=[{"uri": _data_uri(_png_bytes(_halves()), "image/png")}])
    doc["extensionsUsed"] = ["KHR_materials_sheen", "KHR_materials_clearcoat"]
    scene = load_gltf(_write(tmp_path, doc))
    text = "; ".join(scene.unhonoured)
    for name in ("metallic-roughness", "normalTexture", "KHR_materials_sheen",
                 "KHR_materials_clearcoat"):
        assert name in text
    doc["materials"][0] = {"pbrMetallicRoughness": {"metallicFactor": 0.0}}
    doc.pop("extensionsUsed")
    assert load_gltf(_write(tmp_path, doc)).unhonoured == ()


def test_the_default_scene_of_a_multi_scene_file(tmp_path) -> None:
    """``scene`` names the scene loaded (its meshes and lights only)."""
    doc = _quad_document()
    doc["nodes"].append({"mesh": 0, "translation": [0.0, 5.0, 0.0]})
    doc["scenes"] = [{"nodes": [0]}, {"nodes": [1]}]
    doc["scene"] = 1
    scene = load_gltf(_write(tmp_path, doc))
    np.testing.assert_allclose(scene.vertices[:, 1], 5.0)
    doc["scene"] = 0
    np.testing.assert_allclose(load_gltf(_write(tmp_path, doc)).vertices[:, 1], 0.0)


# --------------------------------------------------------------------------------------------
# encoded geometry loads as the plain geometry it encodes


def _mesh_document(pos: np.ndarray, idx: np.ndarray, uv: np.ndarray, *, scale: float = 1.0
                   ) -> dict:
    """A plain .gltf of one mesh (float32 positions, uint32 indices, float32 TEXCOORD_0) under a
    node of uniform ``scale``, with a double-sided grey material."""
    parts = [np.asarray(pos).tobytes(), np.asarray(uv).tobytes(),
             np.asarray(idx, np.uint32).tobytes()]
    views, offset = [], 0
    for p in parts:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(p)})
        offset += len(p)
    ctype = {np.dtype(np.float32): 5126, np.dtype(np.int16): 5122, np.dtype(np.uint16): 5123}
    return {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "scale": [scale] * 3}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1],
                                                "metallicFactor": 0}, "doubleSided": True}],
        "buffers": [{"byteLength": offset, "uri": _data_uri(b"".join(parts))}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": ctype[np.asarray(pos).dtype],
             "count": len(pos), "type": "VEC3"},
            {"bufferView": 1, "componentType": ctype[np.asarray(uv).dtype], "count": len(uv),
             "type": "VEC2", **({"normalized": True} if np.asarray(uv).dtype != np.float32
                                else {})},
            {"bufferView": 2, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
        ],
    }


def _box_geometry() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed box room (inward) as float32 positions, indices and UVs, positions on a
    1/1024 lattice (exact in int16 times 2^-10)."""
    from probegrid.scene import box_mesh

    v, t, uv = box_mesh((-2, 0, -1.5), (2.5, 2.75, 1.5), inward=True)
    return v.astype(np.float32), t.reshape(-1).astype(np.uint32), uv.astype(np.float32)


def test_quantized_and_sparse_geometry_load_as_plain(tmp_path) -> None:
    """KHR_mesh_quantization: int16 positions under a node scale of 2^-10 and normalized
    uint16 UVs load bit for bit as the plain float32 file holding the same values; a sparse
    accessor loads as its dense result."""
    pos, idx, uv = _box_geometry()
    q = np.round(pos * 1024).astype(np.int16)
    quv = np.round(uv * 65535).astype(np.uint16)
    plain = load_gltf(_write(tmp_path, _mesh_document(
        q.astype(np.float32) / np.float32(1024), idx,
        (quv.astype(np.float64) / 65535).astype(np.float32)), "plain.gltf"))
    doc = _mesh_document(q, idx, quv, scale=2.0**-10)
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["KHR_mesh_quantization"]
    quantized = load_gltf(_write(tmp_path, doc, "quantized.gltf"))
    assert quantized.content_hash() == plain.content_hash()
    # sparse: the positions accessor with vertex 3 moved by sparse substitution
    moved = pos.copy()
    moved[3] = [9.0, 9.0, 9.0]
    doc = _mesh_document(pos, idx, uv)
    extra = np.array([3], np.uint32).tobytes() + moved[3].tobytes()
    doc["buffers"].append({"byteLength": len(extra), "uri": _data_uri(extra)})
    doc["bufferViews"] += [{"buffer": 1, "byteOffset": 0, "byteLength": 4},
                           {"buffer": 1, "byteOffset": 4, "byteLength": 12}]
    doc["accessors"][0]["sparse"] = {"count": 1,
                                     "indices": {"bufferView": 3, "componentType": 5125},
                                     "values": {"bufferView": 4}}
    sparse = load_gltf(_write(tmp_path, doc, "sparse.gltf"))
    reference = load_gltf(_write(tmp_path, _mesh_document(moved, idx, uv), "moved.gltf"))
    assert sparse.content_hash() == reference.content_hash()


def _meshopt_document(pos: np.ndarray, idx: np.ndarray, uv: np.ndarray) -> dict:
    """:func:`_mesh_document` with its three buffer views EXT_meshopt_compression-encoded
    (vertex and index codecs) and a fallback buffer without data."""
    import meshoptimizer

    blobs = [meshoptimizer.encode_vertex_buffer(pos, len(pos), 12),
             meshoptimizer.encode_vertex_buffer(uv, len(uv), 8),
             meshoptimizer.encode_index_buffer(idx, len(idx), len(pos))]
    doc = _mesh_document(pos, idx, uv)
    plain_sizes = [v["byteLength"] for v in doc["bufferViews"]]
    data, views, offset = b"", [], 0
    for k, (blob, stride, count, mode) in enumerate(zip(
            blobs, (12, 8, 4), (len(pos), len(uv), len(idx)),
            ("ATTRIBUTES", "ATTRIBUTES", "TRIANGLES"))):
        view = {"buffer": 0, "byteOffset": sum(plain_sizes[:k]), "byteLength": plain_sizes[k],
                "extensions": {"EXT_meshopt_compression": {
                    "buffer": 1, "byteOffset": offset, "byteLength": len(blob),
                    "byteStride": stride, "count": count, "mode": mode}}}
        if mode == "ATTRIBUTES":
            view["byteStride"] = stride
        views.append(view)
        blob = bytes(blob) + b"\0" * (-len(blob) % 4)
        data += blob
        offset += len(blob)
    doc["bufferViews"] = views
    doc["buffers"] = [{"byteLength": sum(plain_sizes),
                       "extensions": {"EXT_meshopt_compression": {"fallback": True}}},
                      {"byteLength": len(data), "uri": _data_uri(data)}]
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_meshopt_compression"]
    return doc


def _draco_document(pos: np.ndarray, idx: np.ndarray, uv: np.ndarray
                    ) -> tuple[dict, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A KHR_draco_mesh_compression .gltf of the mesh, and the geometry Draco decodes it to
    (positions quantized to 14 bits: what a plain file must hold to match it)."""
    import DracoPy

    blob = bytes(DracoPy.encode(pos.astype(np.float64), idx.reshape(-1, 3),
                                tex_coord=uv.astype(np.float64), preserve_order=True,
                                quantization_bits=14))
    decoded = DracoPy.decode(blob)
    ids = {DracoPy.AttributeType(int(a["attribute_type"])).name: int(a["unique_id"])
           for a in decoded.attributes}
    by_id = {int(a["unique_id"]): np.asarray(a["data"], np.float32) for a in decoded.attributes}
    geometry = (by_id[ids["POSITION"]], np.asarray(decoded.faces, np.uint32).reshape(-1),
                by_id[ids["TEX_COORD"]])
    blob += b"\0" * (-len(blob) % 4)
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0,
            "extensions": {"KHR_draco_mesh_compression": {
                "bufferView": 0, "attributes": {"POSITION": ids["POSITION"],
                                                "TEXCOORD_0": ids["TEX_COORD"]}}}}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1],
                                                "metallicFactor": 0}, "doubleSided": True}],
        "buffers": [{"byteLength": len(blob), "uri": _data_uri(blob)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(blob)}],
        "accessors": [
            {"componentType": 5126, "count": len(geometry[0]), "type": "VEC3"},
            {"componentType": 5126, "count": len(geometry[2]), "type": "VEC2"},
            {"componentType": 5125, "count": len(geometry[1]), "type": "SCALAR"}],
        "extensionsUsed": ["KHR_draco_mesh_compression"],
        "extensionsRequired": ["KHR_draco_mesh_compression"],
    }
    return doc, geometry


def test_meshopt_and_draco_load_as_the_plain_geometry_they_decode_to(tmp_path) -> None:
    pos, idx, uv = _box_geometry()
    plain = load_gltf(_write(tmp_path, _mesh_document(pos, idx, uv), "plain.gltf"))
    meshopt = load_gltf(_write(tmp_path, _meshopt_document(pos, idx, uv), "meshopt.gltf"))
    # (the index codec may rotate a triangle's vertices: same triangles, same winding)
    np.testing.assert_array_equal(meshopt.vertices, plain.vertices)
    np.testing.assert_array_equal(np.sort(np.roll(meshopt.triangles, 0, 1).ravel()),
                                  np.sort(plain.triangles.ravel()))
    m_idx = meshopt.triangles.reshape(-1).astype(np.uint32)
    again = load_gltf(_write(tmp_path, _mesh_document(pos, m_idx, uv), "plain2.gltf"))
    assert meshopt.content_hash() == again.content_hash()
    doc, (dpos, didx, duv) = _draco_document(pos, idx, uv)
    draco = load_gltf(_write(tmp_path, doc, "draco.gltf"))
    reference = load_gltf(_write(tmp_path, _mesh_document(dpos, didx, duv), "plain3.gltf"))
    assert draco.content_hash() == reference.content_hash()
    assert np.abs(draco.vertices - plain.vertices).max() < 4.5 * 2**-14  # 14-bit quantization


@pytest.mark.slow
def test_encoded_geometry_bakes_bit_for_bit_as_the_plain_file(tmp_path) -> None:
    """The room as plain float32, as KHR_mesh_quantization, as meshopt and as Draco (each
    against the plain file of what it decodes to): the baked probes are bit-identical."""
    pos, idx, uv = _box_geometry()
    q = np.round(pos * 1024).astype(np.int16)
    quv = np.round(uv * 65535).astype(np.uint16)
    deq = (q.astype(np.float32) / np.float32(1024),
           idx, (quv.astype(np.float64) / 65535).astype(np.float32))
    quant = _mesh_document(q, idx, quv, scale=2.0**-10)
    quant["extensionsUsed"] = quant["extensionsRequired"] = ["KHR_mesh_quantization"]
    draco, dgeo = _draco_document(pos, idx, uv)
    grid = GridSpec.from_counts((-1, 1, -0.5), (1, 2, 0.5), (2, 2, 2))
    st = BakeSettings(bounces=1, seed=5, **{**FAST, "face_size": 8})

    def baked(doc: dict, name: str) -> dict[str, np.ndarray]:
        doc = json.loads(json.dumps(doc))  # a point light in the room (its only light)
        doc["nodes"].append({"translation": [0.3, 2.0, 0.2],
                             "extensions": {"KHR_lights_punctual": {"light": 0}}})
        doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
        doc["extensions"] = {"KHR_lights_punctual": {"lights": [
            {"type": "point", "intensity": 20.0}]}}
        scene = load_gltf(_write(tmp_path, doc, f"{name}.gltf"))
        s = bake(scene, grid, tmp_path / f"{name}.probes", settings=st).store
        arrays = {k: np.asarray(s[k]) for k in s.names}
        assert float(np.abs(arrays["sh"]).max()) > 0  # lit
        return arrays

    for encoded, plain in ((quant, _mesh_document(*deq)),
                           (draco, _mesh_document(*dgeo)),
                           (_meshopt_document(pos, idx, uv), None)):
        a = baked(encoded, "encoded")
        if plain is None:  # meshopt: the plain file of its decoded indices
            m_idx = load_gltf(tmp_path / "encoded.gltf").triangles.reshape(-1).astype(np.uint32)
            plain = _mesh_document(pos, m_idx, uv)
        b = baked(plain, "plain")
        assert a.keys() == b.keys()
        for k in a:
            assert np.array_equal(a[k], b[k]), k
        for p in tmp_path.glob("*.probes*"):
            import shutil

            shutil.rmtree(p, ignore_errors=True)


# --------------------------------------------------------------------------------------------
# EXT_mesh_gpu_instancing: every instance is placed


def _instanced_document(translation: np.ndarray, rotation: np.ndarray | None = None,
                        scale: np.ndarray | None = None) -> dict:
    """:func:`_quad_document` (a 1 m quad at y = 0 facing +Y) under a node at y = 2 whose
    EXT_mesh_gpu_instancing attributes place it ``len(translation)`` times; rotations as
    normalized int16 quaternions (what the extension allows besides float)."""
    doc = _quad_document(size=1.0, material={"doubleSided": True, "pbrMetallicRoughness": {
        "metallicFactor": 0.0}})
    parts = {"TRANSLATION": np.asarray(translation, np.float32)}
    if rotation is not None:
        parts["ROTATION"] = np.round(np.asarray(rotation) * 32767).astype(np.int16)
    if scale is not None:
        parts["SCALE"] = np.asarray(scale, np.float32)
    blob, attrs = b"", {}
    for name, a in parts.items():
        pad = -len(blob) % 4
        blob += b"\0" * pad
        doc["bufferViews"].append({"buffer": 1, "byteOffset": len(blob),
                                   "byteLength": a.nbytes})
        doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1,
                                 "componentType": 5122 if a.dtype == np.int16 else 5126,
                                 "count": len(a), "type": f"VEC{a.shape[1]}",
                                 **({"normalized": True} if a.dtype == np.int16 else {})})
        attrs[name] = len(doc["accessors"]) - 1
        blob += a.tobytes()
    doc["buffers"].append({"byteLength": len(blob), "uri": _data_uri(blob)})
    doc["nodes"] = [{"mesh": 0, "translation": [0.0, 2.0, 0.0],
                     "extensions": {"EXT_mesh_gpu_instancing": {"attributes": attrs}}}]
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_mesh_gpu_instancing"]
    return doc


def test_gpu_instances_each_cast_their_shadow(tmp_path) -> None:
    """Three instances of a 1 m quad under a node at y = 2: at x = -3, at x = 0 turned 45
    degrees about +Y, at x = +3 scaled 2x along x. Sun rays straight up from the floor are
    blocked exactly over each instance's footprint (the turned one a diamond, the scaled one
    2 m wide) and nowhere else; the node's own mesh is not placed besides."""
    s45 = np.sin(np.pi / 8)
    doc = _instanced_document([[-3, 0, 0], [0, 0, 0], [3, 0, 0]],
                              rotation=[[0, 0, 0, 1], [0, s45, 0, np.cos(np.pi / 8)],
                                        [0, 0, 0, 1]],
                              scale=[[1, 1, 1], [1, 1, 1], [2, 1, 1]])
    scene = load_gltf(_write(tmp_path, doc))
    assert scene.n_triangles == 6 and scene.unhonoured == ()
    np.testing.assert_allclose(scene.vertices[:, 1], 2.0, atol=1e-6)
    rng = np.random.default_rng(7)
    o = np.c_[rng.uniform(-5, 5, 20000), np.zeros(20000), rng.uniform(-1.5, 1.5, 20000)]
    x, z = o[:, 0], o[:, 2]
    expected = ((np.abs(x + 3) < 0.5) & (np.abs(z) < 0.5)            # plain
                | (np.abs(x) + np.abs(z) < 0.5 * 2**0.5)             # turned: a diamond
                | ((np.abs(x - 3) < 1.0) & (np.abs(z) < 0.5)))       # scaled along x
    edge = np.minimum.reduce([np.abs(np.abs(x + 3) - 0.5), np.abs(np.abs(z) - 0.5),
                              np.abs(np.abs(x) + np.abs(z) - 0.5 * 2**0.5),
                              np.abs(np.abs(x - 3) - 1.0)]) < 1e-4
    shadow = RayTracer.from_scene(scene).occluded(o, np.tile([0.0, 1.0, 0.0], (len(o), 1)),
                                                  5.0)
    assert np.array_equal(shadow[~edge], expected[~edge])
    assert 0.05 < expected.mean() < 0.3


def test_bad_gpu_instances_are_one_line_errors(tmp_path) -> None:
    doc = _instanced_document([[0, 0, 0], [1, 0, 0]], scale=[[1, 1, 1]])
    with pytest.raises(SceneError, match="different counts") as e:
        load_gltf(_write(tmp_path, doc))
    assert "\n" not in str(e.value)
    doc = _instanced_document([[0, 0, 0]])
    doc["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["SCALE"] = 99
    with pytest.raises(SceneError, match="99 is not an accessor index"):
        load_gltf(_write(tmp_path, doc))
    doc = _instanced_document([[0, np.nan, 0]])
    with pytest.raises(SceneError, match="must be finite"):
        load_gltf(_write(tmp_path, doc))


# --------------------------------------------------------------------------------------------
# EXT_meshopt_compression's filters: each decodes to the values it encoded


def _meshopt_filter(kind: str, values: np.ndarray, stride: int, bits: int) -> np.ndarray:
    """``values (n, 4)`` (OCTAHEDRAL: xyz + w; QUATERNION: xyzw) or ``(n, k)`` (EXPONENTIAL)
    encoded by meshoptimizer's own filter encoder (``meshopt_encodeFilter*`` of its library,
    which the Python wrapper does not expose) into ``(n, stride)`` bytes."""
    import ctypes

    from meshoptimizer._loader import lib

    data = np.ascontiguousarray(values, np.float32)
    n = len(data)
    out = np.zeros((n, stride), np.uint8)
    args = [out.ctypes.data_as(ctypes.c_void_p), ctypes.c_size_t(n), ctypes.c_size_t(stride),
            ctypes.c_int(bits), data.ctypes.data_as(ctypes.POINTER(ctypes.c_float))]
    if kind == "EXPONENTIAL":
        lib.meshopt_encodeFilterExp(*args, ctypes.c_int(0))  # (mode: separate exponents)
    else:
        getattr(lib, {"OCTAHEDRAL": "meshopt_encodeFilterOct",
                      "QUATERNION": "meshopt_encodeFilterQuat"}[kind])(*args)
    return out


def _meshopt_view(doc: dict, view: int, raw: np.ndarray, kind: str) -> None:
    """Buffer view ``view`` of ``doc`` replaced by ``raw`` (``(n, stride)`` filtered bytes)
    meshopt-compressed (ATTRIBUTES mode, filter ``kind``) into a new buffer."""
    import meshoptimizer

    n, stride = raw.shape
    blob = bytes(meshoptimizer.encode_vertex_buffer(raw.view(np.float32) if stride % 4 == 0
                                                    else raw, n, stride))
    size = len(blob)  # (the codec's own length: its tail ends the stream, padding does not)
    blob += b"\0" * (-len(blob) % 4)
    doc["buffers"].append({"byteLength": len(blob), "uri": _data_uri(blob)})
    doc["bufferViews"][view] = {
        "buffer": 0, "byteOffset": 0, "byteLength": n * stride, "byteStride": stride,
        "extensions": {"EXT_meshopt_compression": {
            "buffer": len(doc["buffers"]) - 1, "byteOffset": 0, "byteLength": size,
            "byteStride": stride, "count": n, "mode": "ATTRIBUTES", "filter": kind}}}
    used = set(doc.get("extensionsUsed", [])) | {"EXT_meshopt_compression"}
    doc["extensionsUsed"] = doc["extensionsRequired"] = sorted(used)


def test_meshopt_filters_decode_to_the_values_they_encode(tmp_path) -> None:
    """EXPONENTIAL positions load as the plain positions (23-bit mantissas: to 2^-23
    relative); QUATERNION instance rotations (int16, 12 bits) place the instances as the
    plain float rotations do (to 1e-3 m); OCTAHEDRAL normals (int8 and int16) read back as
    the plain unit normals to their quantization (2 / 2^bits per component)."""
    from probegrid.scene.accessors import float_accessor

    pos, idx, uv = _box_geometry()
    plain = load_gltf(_write(tmp_path, _mesh_document(pos, idx, uv), "plain.gltf"))
    doc = _mesh_document(pos, idx, uv)
    _meshopt_view(doc, 0, _meshopt_filter("EXPONENTIAL", pos, 12, 23), "EXPONENTIAL")
    exp = load_gltf(_write(tmp_path, doc, "exp.gltf"))
    np.testing.assert_allclose(exp.vertices, plain.vertices, rtol=2**-22, atol=0)
    assert not np.array_equal(_meshopt_filter("EXPONENTIAL", pos, 12, 23).view(np.float32),
                              pos)  # (the filter changes the bytes: undone on load)

    rng = np.random.default_rng(5)
    q = rng.normal(size=(6, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = np.c_[np.arange(6) * 3.0, np.zeros(6), np.zeros(6)]
    floats = _instanced_document(t)
    floats["accessors"].append({"bufferView": len(floats["bufferViews"]),
                                "componentType": 5126, "count": 6, "type": "VEC4"})
    blob = q.astype(np.float32).tobytes()
    floats["buffers"].append({"byteLength": len(blob), "uri": _data_uri(blob)})
    floats["bufferViews"].append({"buffer": len(floats["buffers"]) - 1, "byteOffset": 0,
                                  "byteLength": len(blob)})
    ext = floats["nodes"][0]["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    ext["ROTATION"] = len(floats["accessors"]) - 1
    reference = load_gltf(_write(tmp_path, floats, "rot.gltf"))
    coded = json.loads(json.dumps(floats))
    coded["accessors"][-1].update(componentType=5122, normalized=True)
    _meshopt_view(coded, len(coded["bufferViews"]) - 1,
                  _meshopt_filter("QUATERNION", q, 8, 12), "QUATERNION")
    quat = load_gltf(_write(tmp_path, coded, "quat.gltf"))
    assert quat.n_triangles == reference.n_triangles == 12

    def by_instance(scene: Scene) -> np.ndarray:  # (instances in the loader's order: sorted)
        v = scene.vertices.reshape(6, -1, 3)
        return v[np.argsort(v[:, :, 0].mean(axis=1))]

    err = np.abs(by_instance(quat) - by_instance(reference)).max()
    assert 0 < err < 1e-3, err

    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    for stride, bits, ctype in ((4, 8, 5120), (8, 16, 5122)):
        raw = _meshopt_filter("OCTAHEDRAL", np.c_[nrm, np.zeros(50)], stride, bits)
        d = _mesh_document(pos, idx, uv)
        d["accessors"].append({"bufferView": 3, "componentType": ctype, "normalized": True,
                               "count": 50, "type": "VEC3"})
        d["bufferViews"].append({})
        _meshopt_view(d, 3, raw, "OCTAHEDRAL")
        buffers = [base64.b64decode(b["uri"].split(",", 1)[1]) if "uri" in b else b""
                   for b in d["buffers"]]
        got = float_accessor(d, buffers, 3, "normals")
        np.testing.assert_allclose(got, nrm, atol=2.0 / 2 ** (bits - 1))
        np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=2.0 / 2 ** (bits - 1))
        load_gltf(_write(tmp_path, d, f"oct{bits}.gltf"))  # (a file with them loads)
