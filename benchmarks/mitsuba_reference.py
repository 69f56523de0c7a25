"""A path-traced reference for probe bakes: Mitsuba 3 renders the incoming cube at probe points.

Benchmark-only helper (``pip install mitsuba``; variant ``scalar_rgb``, whose LLVM sibling
crashes on some machines). It converts a probegrid :class:`~probegrid.scene.Scene` and
:class:`~probegrid.bake.environment.Environment` into a Mitsuba scene with the *same* physics as
the bake, and renders, at every probe, six 90-degree perspective sensors whose pixels are
exactly probegrid's cube texels (``probegrid.core.cubemap``: faces +X,-X,+Y,-Y,+Z,-Z, row 0 on
top, texel centres at ``u = 2(col + 0.5)/n - 1``, OpenGL/KTX2 face table).

Conversion (what is the same, and what is refused rather than guessed)
----------------------------------------------------------------------
* Triangles: one PLY per material, flat (face) normals, glTF winding kept, so Mitsuba's front
  side is probegrid's (``normalize((b - a) x (c - a))``). Single-sided materials reflect on the
  front only (a back hit is black in both tools); double-sided materials get Mitsuba's
  ``twosided`` BSDF (glTF: a double-sided back face is shaded with the flipped normal).
  Emission leaves the front only, whatever ``doubleSided`` (probegrid's convention,
  :mod:`probegrid.bake.emitters`, README "Conventions"), as Mitsuba's ``area`` emitter does.
  (A backward-emitting copy of a double-sided emitter would light the Cornell box's ceiling
  behind the panel, 3 % of what the probes see of light reflected once; ``CONVERTER_VERSION``
  in the cache key keeps references converted otherwise out.)
* Lambertian albedo ``baseColorFactor.rgb * baseColorTexture.rgb`` (the linear texture probegrid
  decoded, premultiplied by the factor, bilinear, its wrap mode; glTF UVs, whose (0, 0) is the
  image's first row, as Mitsuba's bitmap reads them); emission ``emissiveFactor *
  emissiveStrength * emissiveTexture`` as an ``area`` emitter's radiance. Vertex colours other
  than white, and textures with different wrap modes along u and v, are refused.
* Punctual lights (``probegrid.core.lights``: candela and lux; radiance in cd/m^2): a point
  light of ``I`` cd is Mitsuba's ``point`` emitter of intensity ``I`` (irradiance ``I / d^2`` in
  both), a directional light of ``E`` lux its ``directional`` emitter of irradiance ``E``. The
  glTF ``range`` window ``clamp(1 - (d/range)^4, 0, 1)`` has no Mitsuba counterpart, so a light
  with a range is refused: :func:`without_light_ranges` gives the scene both tools then bake.
  Spot lights are refused (Mitsuba's cone falloff is linear in angle, glTF's quadratic in cosine).
* The environment: an ``envmap`` lat-long bitmap filled by evaluating probegrid's own
  environment (rotation and intensity included) at the bitmap's pixel directions, 2x2
  supersampled; Mitsuba's lat-long is ``u = atan2(x, -z) / 2pi``, ``v = acos(y) / pi``
  (checked numerically by :func:`check_orientation`).

Sensors: Mitsuba's ``look_at`` camera looking along the face normal with up ``-FACE_V`` sees the
face mirrored left-right (cube maps are left-handed), so its image is flipped back. All sensors
of a render are one ``batch`` sensor (one film, many threads), box pixel filter: a pixel is the
mean radiance over its footprint, which is what a texel of a probegrid cube estimates.

References: Mitsuba 3 documentation (plugins ``path``, ``envmap``, ``point``, ``directional``,
``area``, ``batch``, ``perspective``); KHR_lights_punctual; glTF 2.0.
"""

from __future__ import annotations

import dataclasses
import hashlib
import tempfile
import time
from pathlib import Path
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.core.cubemap import FACE_NORMALS, FACE_V, texel_directions, texel_solid_angles
from probegrid.core.lights import DirectionalLight, PointLight
from probegrid.scene import Material, Scene

__all__ = ["CubeRender", "MitsubaReference", "check_environment_energy", "check_furnace",
           "check_orientation", "without_light_ranges"]

#: Bumped when the conversion changes (part of every cache key).
CONVERTER_VERSION = "2"


def _mi() -> Any:
    import mitsuba as mi

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


def without_light_ranges(scene: Scene) -> Scene:
    """``scene`` with every light's glTF ``range`` removed (pure inverse-square falloff)."""
    lights = tuple(dataclasses.replace(lt, range=None) if getattr(lt, "range", None) is not None
                   else lt for lt in scene.lights)
    return dataclasses.replace(scene, lights=lights)


# ------------------------------------------------------------------------------ conversion
def _write_ply(path: Path, positions: NDArray[np.float64], uvs: NDArray[np.float64] | None) -> None:
    """Binary PLY of unshared-vertex triangles (3 consecutive vertices per face)."""
    nv = len(positions)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if uvs is not None:
        fields += [("u", "<f4"), ("v", "<f4")]
    vert = np.empty(nv, dtype=fields)
    vert["x"], vert["y"], vert["z"] = positions.T
    if uvs is not None:
        vert["u"], vert["v"] = uvs.T
    faces = np.empty(nv // 3, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = np.arange(nv, dtype=np.int32).reshape(-1, 3)
    props = "".join(f"property float {name}\n" for name, _ in fields)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {nv}\n{props}"
              f"element face {nv // 3}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vert.tobytes())
        f.write(faces.tobytes())


def _rgb(value: Any) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(x) for x in np.asarray(value, dtype=np.float64)]}


def _bitmap(mi: Any, data: NDArray[np.float32], wrap: tuple[str, str], what: str) -> dict:
    if wrap[0] != wrap[1]:
        raise ValueError(f"{what}: different wrap modes along u and v ({wrap}) are not supported")
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(data, dtype=np.float32)),
            "raw": True, "filter_type": "bilinear", "wrap_mode": wrap[0]}


def environment_latlong(env: Environment, *, width: int | None = None) -> NDArray[np.float32]:
    """Mitsuba's lat-long bitmap ``(width/2, width, 3)`` of ``env`` (see the module docstring)."""
    if width is None:
        width = 4 * int(env.faces.shape[1]) if env.faces is not None else 8
    h, w = width // 2, width
    sampler = env.sampler()
    acc = np.zeros((h, w, 3), dtype=np.float64)
    for dy in (0.25, 0.75):  # 2x2 supersampling (a loop over 4 offsets, not over pixels)
        for dx in (0.25, 0.75):
            theta = (np.arange(h) + dy)[:, None] / h * np.pi
            phi = (np.arange(w) + dx)[None, :] / w * 2.0 * np.pi
            d = np.stack(np.broadcast_arrays(np.sin(theta) * np.sin(phi), np.cos(theta),
                                             -np.sin(theta) * np.cos(phi)), axis=-1)
            acc += sampler.radiance(d)
    return (acc / 4.0).astype(np.float32)


def scene_dict(scene: Scene, environment: Environment | None, directory: Path, *,
               max_depth: int) -> dict[str, Any]:
    """The Mitsuba scene description of ``scene`` (PLY files written into ``directory``)."""
    mi = _mi()
    d: dict[str, Any] = {"type": "scene",
                         "integrator": {"type": "path", "max_depth": int(max_depth)}}
    if scene.colors is not None and not np.all(scene.colors[:, :3] == 1.0):
        raise ValueError("vertex colours (COLOR_0) other than white are not supported")
    tris = scene.triangles
    for mid, mat in enumerate(scene.materials):
        sel = np.flatnonzero(scene.material == mid)
        if not sel.size:
            continue
        pos = scene.vertices[tris[sel]].reshape(-1, 3)
        textured = mat.base_color_texture is not None or mat.emissive_texture is not None
        if textured and scene.uvs is None:
            raise ValueError(f"material {mat.name!r} has a texture but the scene has no UVs")
        uv = scene.uvs[tris[sel]].reshape(-1, 2) if textured else None
        if mat.base_color_texture is not None:
            tex = mat.base_color_texture[..., :3] * mat.base_color[:3].astype(np.float32)
            refl = _bitmap(mi, tex, mat.base_color_wrap, f"material {mat.name!r}")
        else:
            refl = _rgb(mat.base_color[:3])
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": refl}
        if mat.double_sided:
            bsdf = {"type": "twosided", "material": bsdf}
        emitter = None
        if mat.emissive_texture is not None and np.any(mat.emissive > 0):
            tex = mat.emissive_texture * mat.emissive.astype(np.float32)
            emitter = {"type": "area",
                       "radiance": _bitmap(mi, tex, mat.emissive_wrap, f"material {mat.name!r}")}
        elif np.any(mat.emissive > 0):
            emitter = {"type": "area", "radiance": _rgb(mat.emissive)}
        file = directory / f"m{mid}.ply"
        _write_ply(file, pos, uv)
        shape: dict[str, Any] = {"type": "ply", "filename": str(file), "face_normals": True,
                                 "bsdf": bsdf}
        if emitter is not None:  # (front only, module docstring)
            shape["emitter"] = emitter
        d[f"shape_{mid}"] = shape
    for i, light in enumerate(scene.lights):
        power = np.asarray(light.color, dtype=np.float64) * light.intensity
        if isinstance(light, PointLight):
            if light.range is not None:
                raise ValueError("a light with a glTF range has no Mitsuba counterpart; "
                                 "bake and render without_light_ranges(scene)")
            d[f"light_{i}"] = {"type": "point", "position": [float(x) for x in light.position],
                               "intensity": _rgb(power)}
        elif isinstance(light, DirectionalLight):
            d[f"light_{i}"] = {"type": "directional",
                               "direction": [float(x) for x in light.direction],
                               "irradiance": _rgb(power)}
        else:
            raise TypeError(f"{type(light).__name__} is not supported by the Mitsuba reference")
    if environment is not None and not environment.is_black:
        if environment.faces is None:
            d["environment"] = {"type": "constant",
                                "radiance": _rgb(environment.color * environment.intensity)}
        else:
            d["environment"] = {"type": "envmap",
                                "bitmap": mi.Bitmap(environment_latlong(environment))}
    return d


# ------------------------------------------------------------------------------ rendering
@dataclasses.dataclass(frozen=True)
class CubeRender:
    """Incoming cubes ``(P, 6, n, n, 3)`` float32 and the wall time of the render (s)."""

    cubes: NDArray[np.float32]
    seconds: float
    spp: int
    max_depth: int


def _sensor(mi: Any, positions: NDArray[np.float64], n: int) -> dict[str, Any]:
    sensors: dict[str, Any] = {
        "type": "batch",
        "film": {"type": "hdrfilm", "width": 6 * n * len(positions), "height": n,
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }
    for p, o in enumerate(positions):
        for f in range(6):
            fwd, up = FACE_NORMALS[f], -FACE_V[f]
            sensors[f"s{p:06d}_{f}"] = {
                "type": "perspective", "fov": 90.0, "fov_axis": "x",
                "near_clip": 1e-6, "far_clip": 1e30,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[float(x) for x in o], target=[float(x) for x in o + fwd],
                    up=[float(x) for x in up]),
                "film": {"type": "hdrfilm", "width": n, "height": n,
                         "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            }
    return sensors


class MitsubaReference:
    """A scene loaded into Mitsuba once, rendering probe cubes at any depth and sample count."""

    def __init__(self, scene: Scene, environment: Environment | None = None) -> None:
        self.scene = scene
        self.environment = environment
        self._tmp = tempfile.TemporaryDirectory(prefix="pg-mitsuba-")
        self._loaded: dict[int, Any] = {}

    def close(self) -> None:
        self._tmp.cleanup()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _scene(self, max_depth: int) -> Any:
        if max_depth not in self._loaded:
            mi = _mi()
            d = scene_dict(self.scene, self.environment, Path(self._tmp.name),
                           max_depth=max_depth)
            self._loaded[max_depth] = mi.load_dict(d)
        return self._loaded[max_depth]

    def render(self, positions: NDArray[np.float64], face_size: int, *, spp: int,
               max_depth: int, seed: int = 0, chunk: int = 64) -> CubeRender:
        """Incoming cubes at ``positions (P, 3)``; the time includes loading the scene."""
        mi = _mi()
        t0 = time.perf_counter()
        sc = self._scene(max_depth)
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        n = int(face_size)
        out = np.empty((len(pos), 6, n, n, 3), dtype=np.float32)
        for start in range(0, len(pos), chunk):  # a loop over sensor batches, not texels
            part = pos[start:start + chunk]
            sensor = mi.load_dict(_sensor(mi, part, n))
            img = np.array(mi.render(sc, sensor=sensor, spp=int(spp), seed=int(seed) + start),
                           dtype=np.float32)[..., :3]
            cubes = img.reshape(n, len(part), 6, n, 3).transpose(1, 2, 0, 3, 4)
            out[start:start + len(part)] = cubes[:, :, :, ::-1]  # mirrored faces, flipped back
        return CubeRender(out, time.perf_counter() - t0, int(spp), int(max_depth))

    def punctual_diffuse(self, positions: NDArray[np.float64], size: int) -> NDArray[np.float32]:
        """``(P, 6, size, size, 3)`` irradiance / pi at the probes from the punctual lights they
        see directly: ``E_perp max(0, n . l) / pi`` at each texel's centre normal.

        A camera ray never hits a delta light, so a rendered cube lacks the light a probe
        receives straight from point and directional lights; this is that part (probegrid splats
        it into the cube, which its diffuse filter turns into the same closed form). Visibility is
        Mitsuba's own shadow ray (``Scene.ray_test``), one per probe and light.
        """
        mi = _mi()
        sc = self._scene(1)
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        nrm = texel_directions(size)  # (6, s, s, 3)
        out = np.zeros((len(pos), 6, size, size, 3), dtype=np.float64)
        extent = float(np.linalg.norm(np.ptp(self.scene.bounds, axis=0)))
        for light in self.scene.lights:  # loops over lights and probes (a few), not texels
            power = np.asarray(light.color, dtype=np.float64) * light.intensity
            for p, o in enumerate(pos):
                if isinstance(light, PointLight):
                    to = np.asarray(light.position, dtype=np.float64) - o
                    dist = float(np.linalg.norm(to))
                    l, e_perp, tmax = to / dist, power / dist**2, dist * (1.0 - 1e-5)
                else:
                    l = -np.asarray(light.direction, dtype=np.float64)
                    l, e_perp, tmax = l / np.linalg.norm(l), power, 4.0 * extent + 1.0
                ray = mi.Ray3f(mi.ScalarPoint3f(*o), mi.ScalarVector3f(*l))
                ray.maxt = tmax
                if sc.ray_test(ray):
                    continue
                out[p] += np.maximum(nrm @ l, 0.0)[..., None] * e_perp / np.pi
        return out.astype(np.float32)


def cache_key(scene: Scene, environment: Environment | None, positions: NDArray[np.float64],
              **settings: Any) -> str:
    """Content key of a reference render: scene, environment, probe points and settings."""
    from probegrid.bake.driver import environment_hash

    mi = _mi()
    h = hashlib.sha256()
    h.update(scene.content_hash().encode())
    h.update(environment_hash(environment or Environment()).encode())
    h.update(np.ascontiguousarray(positions, dtype="<f8").tobytes())
    h.update(repr(sorted(settings.items())).encode())
    h.update(f"mitsuba {mi.__version__} {mi.variant()} converter {CONVERTER_VERSION}".encode())
    return h.hexdigest()[:24]


# ------------------------------------------------------------------------------ checks
def check_orientation(*, face_size: int = 8) -> dict[str, float]:
    """Prove that the rendered cubes are probegrid's cubes; raise AssertionError if not.

    1. A lopsided environment (radiance ``(1.5 + x, 1.5 + y, 1.5 + z)`` of the world direction,
       given to Mitsuba as probegrid's own environment cube) rendered at two probes: every texel
       of all twelve faces must read its own direction (``probegrid.core.cubemap
       .texel_directions``), so faces, rows, columns, the batch order and the lat-long
       convention are all right.
    2. A small emissive square off-axis (towards ``(1, 0.5, -0.3)``) of probe A and of probe B,
       which sees it from elsewhere: the solid-angle-weighted centroid of each rendered cube must point at
       the square's centre (geometry, winding and the front side of the area light).
    Returns the worst errors found.
    """
    n = int(face_size)
    # 1. environment: a cube of texel directions at 64^2 (bilinear in probegrid, near-linear data)
    m = 64
    dirs = texel_directions(m)
    env = Environment(faces=(1.5 + dirs).astype(np.float32))
    tri = Scene.from_arrays([[1e3, 1e3, 1e3], [1e3 + 1e-3, 1e3, 1e3], [1e3, 1e3 + 1e-3, 1e3]],
                            [[0, 1, 2]])  # a speck far away: Mitsuba wants a shape
    with MitsubaReference(tri, env) as ref:
        got = ref.render(np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1]]), n, spp=256,
                         max_depth=1).cubes
    want = 1.5 + texel_directions(n)
    env_err = float(np.abs(got - want[None]).max())
    assert env_err < 0.05, f"the Mitsuba cube does not match probegrid's face table ({env_err})"
    # 2. an emissive square facing the probes (single-sided, its front toward -target)
    target = np.array([1.0, 0.5, -0.3])
    target /= np.linalg.norm(target)
    centre = 2.0 * target
    a = np.cross(target, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(target, a)
    s = 0.1
    quad = np.array([centre - s * a - s * b, centre + s * a - s * b, centre + s * a + s * b,
                     centre - s * a + s * b])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    nrm = np.cross(quad[1] - quad[0], quad[2] - quad[0])
    if nrm @ target > 0:  # front toward the probes
        tris = tris[:, ::-1]
    lamp = Scene.from_arrays(quad, tris, materials=[Material.diffuse(0.0, emission=1.0)])
    probes = np.array([[0.0, 0.0, 0.0], 1.0 * a + 0.5 * b])  # both in front of the square
    with MitsubaReference(lamp, None) as ref:
        cubes = ref.render(probes, max(n, 16), spp=16, max_depth=1).cubes
    w = texel_solid_angles(max(n, 16))[..., None] * cubes[..., :1]
    d = texel_directions(max(n, 16))
    worst = 0.0
    for p in range(len(probes)):
        c = (w[p] * d).sum(axis=(0, 1, 2))
        expect = centre - probes[p]
        cosang = float(c @ expect / (np.linalg.norm(c) * np.linalg.norm(expect)))
        worst = max(worst, float(np.degrees(np.arccos(min(1.0, cosang)))))
    assert worst < 2.0, f"an emitter lands {worst:.1f} degrees off its direction in the cube"
    return {"environment_max_abs_error": env_err, "emitter_direction_error_deg": worst}


def check_environment_energy(environment: Environment, *, albedo: float = 0.5) -> float:
    """The converted environment's energy, against probegrid's own integral: a probe 1 unit
    above a wide Lambertian floor (albedo ``albedo``) under ``environment`` sees, looking
    straight down, the radiance ``albedo * E_up / pi``, with ``E_up / pi`` the exact diffuse
    integral of the environment cube at +Y (:func:`probegrid.core.diffuse.diffuse_exact`).
    Mitsuba renders it at max depth 2; returns the worst relative error of the RGB channels
    (the floor's finite size and the probe's own tiny shadow cost well under 1 %)."""
    from probegrid.core.diffuse import diffuse_exact

    if environment.faces is None:
        want = albedo * environment.color * environment.intensity
    else:
        plus_y = diffuse_exact(environment.faces, 1)[2, 0, 0].astype(np.float64)
        # (rotation about +Y leaves the +Y irradiance unchanged)
        want = albedo * plus_y * environment.intensity
    size = 1e4
    floor = Scene.from_arrays([[-size, 0, -size], [size, 0, -size], [size, 0, size],
                               [-size, 0, size]], [[0, 2, 1], [0, 3, 2]],
                              materials=[Material.diffuse(albedo)])
    with MitsubaReference(floor, environment) as ref:
        cube = ref.render(np.array([[0.0, 1.0, 0.0]]), 4, spp=2048, max_depth=2).cubes
    got = cube[0, 3, 1:3, 1:3].mean(axis=(0, 1)).astype(np.float64)  # -Y face, central texels
    err = float(np.max(np.abs(got - want) / np.maximum(want, 1e-12)))
    assert err < 0.02, f"the Mitsuba environment's energy is {err:.1%} off probegrid's"
    return err


def check_furnace(*, albedo: float = 0.6, emission: float = 1.0) -> float:
    """Convergence and units of the converted materials: inside a closed box whose walls emit
    ``Le`` and reflect ``rho`` (:func:`probegrid.scene.box_scene`), every direction reads the
    infinite series ``Le / (1 - rho)``. Rendered at max depth 64 (``rho^64`` is nothing);
    returns the relative error of the mean over the cube."""
    from probegrid.scene import box_scene

    box = box_scene((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), albedo=albedo, emission=emission)
    with MitsubaReference(box, None) as ref:
        cube = ref.render(np.array([[0.1, -0.2, 0.3]]), 4, spp=256, max_depth=64).cubes
    err = float(abs(cube.mean() / (emission / (1.0 - albedo)) - 1.0))
    assert err < 0.01, f"the Mitsuba furnace reads {err:.1%} off Le / (1 - rho)"
    return err
