"""The project's own sample data: an analytic HDR sky and a small glTF room, made from code.

``python -m probegrid.jobs.samples [DIR]`` regenerates ``data/sample_room.glb`` and
``data/sample_sky.hdr`` (default ``DIR`` = the repository's ``data/``). Both are deterministic:
the same code writes the same bytes.

The sky (:func:`sample_sky`)
----------------------------
A lat-long (equirect) image in the project's layout (:mod:`probegrid.core.layouts`: centre column =
+X, ``u`` increasing toward +Z, top row = +Y), linear Rec.709 radiance in relative units:

* above the horizon a gradient from a pale horizon ``(1.10, 1.15, 1.20)`` to a blue zenith
  ``(0.30, 0.50, 0.95)``, blended by ``elevation_sine ** 0.5``, plus a soft glow around the sun
  ``0.6 exp(-angle / 0.2 rad)``;
* below the horizon a grey-brown ground ``(0.22, 0.20, 0.18)``, darkening to 60 % at the nadir;
* a sun disc of angular radius 1.5 degrees and radiance ``1500 (1.00, 0.93, 0.82)`` toward
  :data:`SUN_DIRECTION` (elevation 35 degrees, azimuth 70 degrees from +X toward +Z, so it shines
  through the room's window), its edge anti-aliased over one pixel. Its irradiance at normal
  incidence is about ``1500 * pi * radius^2 ~= 3.2``, comparable to the sky's.

The room (:func:`sample_room_gltf`)
-----------------------------------
A 4 x 3 x 4 m room, ``x, z in [-2, 2]``, ``y in [0, 3]`` (glTF metres, +Y up), walls facing
inward and single-sided (so a probe outside sees back faces):

* floor: white with an sRGB 16 x 16 checker ``baseColorTexture`` tiled 4 x 4 (REPEAT sampler);
  ceiling and back wall (z = -2) white (0.8); left wall (x = -2) red (0.8, 0.1, 0.1); right wall
  (x = +2) green (0.1, 0.8, 0.1);
* front wall (z = +2) white with a 2 x 1.2 m window opening (``x in [-1, 1]``,
  ``y in [1, 2.2]``) to the sky;
* a 1 x 1 m ceiling panel at y = 2.98 facing down, ``emissiveFactor (1, 0.9, 0.8)`` with
  ``KHR_materials_emissive_strength`` 5 (radiance 5, 4.5, 4);
* two boxes (one unit-cube mesh instanced by two nodes with rotation and scale, under a parent
  node with its own translation, exercising node transforms);
* a ``KHR_lights_punctual`` point light "Lamp" of 8 cd, colour (1, 0.85, 0.7), range 8 m, at
  (0, 2.2, 0.5).

The .glb is written by hand (glTF 2.0 JSON + one binary buffer, PNG encoded with zlib); the
project's loader (:func:`probegrid.scene.load_gltf`) and trimesh read it back.

Reference: glTF 2.0 specification ("Binary glTF Layout", accessors, samplers); PNG
specification (ISO/IEC 15948) for the minimal IHDR/IDAT/IEND encoder.
"""

from __future__ import annotations

import json
import math
import struct
import sys
import zlib
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.layouts import equirect_directions
from probegrid.scene import box_mesh, quad_mesh

__all__ = [
    "LAMP_INTENSITY",
    "LAMP_POSITION",
    "PANEL_EMISSION",
    "ROOM_MAX",
    "ROOM_MIN",
    "SUN_DIRECTION",
    "SUN_RADIUS",
    "WINDOW",
    "main",
    "sample_room_glb_bytes",
    "sample_room_gltf",
    "sample_sky",
    "write_sample_data",
    "write_sample_sky",
]


def _unit(x: float, y: float, z: float) -> tuple[float, float, float]:
    n = math.sqrt(x * x + y * y + z * z)
    return (x / n, y / n, z / n)


_SUN_ELEVATION: Final[float] = math.radians(35.0)
_SUN_AZIMUTH: Final[float] = math.radians(70.0)
#: Unit direction toward the sun (world, +Y up).
SUN_DIRECTION: Final[tuple[float, float, float]] = _unit(
    math.cos(_SUN_ELEVATION) * math.cos(_SUN_AZIMUTH),
    math.sin(_SUN_ELEVATION),
    math.cos(_SUN_ELEVATION) * math.sin(_SUN_AZIMUTH),
)
#: Angular radius of the sun disc, radians.
SUN_RADIUS: Final[float] = math.radians(1.5)
_SUN_RADIANCE: Final[tuple[float, float, float]] = (1500.0, 1395.0, 1230.0)
_HORIZON: Final[tuple[float, float, float]] = (1.10, 1.15, 1.20)
_ZENITH: Final[tuple[float, float, float]] = (0.30, 0.50, 0.95)
_GROUND: Final[tuple[float, float, float]] = (0.22, 0.20, 0.18)

#: Room interior corners (metres).
ROOM_MIN: Final[tuple[float, float, float]] = (-2.0, 0.0, -2.0)
ROOM_MAX: Final[tuple[float, float, float]] = (2.0, 3.0, 2.0)
#: Window opening in the front wall z = +2: (x0, x1, y0, y1).
WINDOW: Final[tuple[float, float, float, float]] = (-1.0, 1.0, 1.0, 2.2)
LAMP_POSITION: Final[tuple[float, float, float]] = (0.0, 2.2, 0.5)
LAMP_INTENSITY: Final[float] = 8.0
_LAMP_COLOR: Final[tuple[float, float, float]] = (1.0, 0.85, 0.7)
_LAMP_RANGE: Final[float] = 8.0
_PANEL_FACTOR: Final[tuple[float, float, float]] = (1.0, 0.9, 0.8)
_PANEL_STRENGTH: Final[float] = 5.0
#: Emitted radiance of the ceiling panel (emissiveFactor * emissiveStrength).
PANEL_EMISSION: Final[tuple[float, float, float]] = tuple(  # type: ignore[assignment]
    f * _PANEL_STRENGTH for f in _PANEL_FACTOR
)


# --------------------------------------------------------------------------------------------
# sky


def sample_sky(width: int = 512) -> NDArray[np.float32]:
    """The analytic sample sky as a lat-long image (see the module docstring).

    Parameters
    ----------
    width : int
        Image width, even, >= 8; the height is ``width // 2``.

    Returns
    -------
    (width // 2, width, 3) float32
        Linear radiance.
    """
    if (
        not isinstance(width, (int, np.integer))
        or isinstance(width, bool)
        or width < 8
        or width % 2
    ):
        raise ValueError(f"width must be an even integer >= 8, got {width!r}.")
    d = equirect_directions(width // 2, width)
    y = d[..., 1:2]
    sun = np.asarray(SUN_DIRECTION)
    angle = np.arccos(np.clip(d @ sun, -1.0, 1.0))[..., None]
    above = np.maximum(y, 0.0) ** 0.5
    sky = np.asarray(_HORIZON) + (np.asarray(_ZENITH) - np.asarray(_HORIZON)) * above
    sky = sky + 0.6 * np.exp(-angle / 0.2)
    ground = np.asarray(_GROUND) * (1.0 + 0.4 * np.minimum(y, 0.0))
    image = np.where(y >= 0.0, sky, ground)
    pixel = 2.0 * np.pi / width
    coverage = np.clip((SUN_RADIUS - angle) / pixel + 0.5, 0.0, 1.0)
    image = image * (1.0 - coverage) + np.asarray(_SUN_RADIANCE) * coverage
    return image.astype(np.float32)


def write_sample_sky(path: str | Path, *, width: int = 512) -> Path:
    """Write :func:`sample_sky` as a Radiance .hdr through :mod:`probegrid.imageio`."""
    from probegrid.imageio import write_image

    out = Path(path)
    write_image(out, sample_sky(width))
    return out


# --------------------------------------------------------------------------------------------
# PNG and glTF encoders


def _png_rgb8(pixels: NDArray[np.uint8]) -> bytes:
    """A minimal 8-bit RGB PNG (filter type 0 on every row)."""
    h, w, _ = pixels.shape

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    raw = np.concatenate([np.zeros((h, 1), np.uint8), pixels.reshape(h, w * 3)], axis=1)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 9))
        + chunk(b"IEND", b"")
    )


def _checker(size: int = 16, cell: int = 4) -> NDArray[np.uint8]:
    """An sRGB-encoded grey checker, (size, size, 3) uint8."""
    i = np.arange(size) // cell
    odd = (i[:, None] + i[None, :]) % 2 == 1
    return np.where(odd[..., None], np.uint8(150), np.uint8(225)).repeat(3, axis=2)


class _GlbWriter:
    """Accumulates one binary buffer, its bufferViews and accessors."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        self.blob += b"\x00" * (-len(self.blob) % 4)
        v = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.blob += data
        self.views.append(v)
        return len(self.views) - 1

    def accessor(
        self, array: NDArray, kind: str, *, bounds: bool = False, index: bool = False
    ) -> int:
        if index:
            a = np.ascontiguousarray(array, dtype="<u2").reshape(-1)
            component = 5123
        else:
            a = np.ascontiguousarray(array, dtype="<f4")
            component = 5126
        acc = {
            "bufferView": self.view(a.tobytes(), 34963 if index else 34962),
            "componentType": component,
            "count": len(a),
            "type": kind,
        }
        if bounds:
            acc["min"] = [float(x) for x in a.min(axis=0)]
            acc["max"] = [float(x) for x in a.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def primitive(self, parts: list[tuple[NDArray, NDArray, NDArray]], material: int) -> dict:
        """A triangle primitive from (vertices, triangles, uvs) parts; flat normals."""
        verts, norms, uvs, tris = [], [], [], []
        count = 0
        for v, t, uv in parts:
            n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
            vn = np.zeros_like(v)
            vn[t.reshape(-1)] = np.repeat(n, 3, axis=0)  # quads/boxes: vertices per flat face
            verts.append(v)
            norms.append(vn)
            uvs.append(uv)
            tris.append(t + count)
            count += len(v)
        return {
            "attributes": {
                "POSITION": self.accessor(np.concatenate(verts), "VEC3", bounds=True),
                "NORMAL": self.accessor(np.concatenate(norms), "VEC3"),
                "TEXCOORD_0": self.accessor(np.concatenate(uvs), "VEC2"),
            },
            "indices": self.accessor(np.concatenate(tris), "SCALAR", index=True),
            "material": material,
        }


def _quad(corner: ArrayLike, edge_u: ArrayLike, edge_v: ArrayLike, uv_scale: float = 1.0):
    v, t, uv = quad_mesh(corner, edge_u, edge_v)
    return v, t, uv * uv_scale


def _quat_y(degrees: float) -> list[float]:
    h = math.radians(degrees) / 2.0
    return [0.0, math.sin(h), 0.0, math.cos(h)]


def sample_room_glb_bytes() -> bytes:
    """The sample room as .glb bytes (deterministic; see the module docstring)."""
    x0, y0, z0 = ROOM_MIN
    x1, y1, z1 = ROOM_MAX
    wx0, wx1, wy0, wy1 = WINDOW
    w = _GlbWriter()
    # Faces point into the room: edge_u x edge_v is the inward normal.
    floor = _quad((x0, y0, z0), (0, 0, z1 - z0), (x1 - x0, 0, 0), uv_scale=4.0)  # +Y
    ceiling = _quad((x0, y1, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0))  # -Y
    back = _quad((x0, y0, z0), (x1 - x0, 0, 0), (0, y1 - y0, 0))  # +Z
    left = _quad((x0, y0, z1), (0, 0, z0 - z1), (0, y1 - y0, 0))  # +X
    right = _quad((x1, y0, z0), (0, 0, z1 - z0), (0, y1 - y0, 0))  # -X

    def front(xa: float, xb: float, ya: float, yb: float):
        return _quad((xb, ya, z1), (xa - xb, 0, 0), (0, yb - ya, 0))

    front_parts = [
        front(x0, x1, y0, wy0),
        front(x0, x1, wy1, y1),
        front(x0, wx0, wy0, wy1),
        front(wx1, x1, wy0, wy1),
    ]
    panel = _quad((-0.5, y1 - 0.02, -0.5), (1.0, 0, 0), (0, 0, 1.0))  # -Y
    cube = box_mesh((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))

    png = w.view(_png_rgb8(_checker()))
    room_mesh = {
        "name": "Room",
        "primitives": [
            w.primitive([floor], 0),
            w.primitive([ceiling, back, *front_parts], 1),
            w.primitive([left], 2),
            w.primitive([right], 3),
        ],
    }
    panel_mesh = {"name": "Panel", "primitives": [w.primitive([panel], 4)]}
    box_mesh_json = {"name": "Box", "primitives": [w.primitive([cube], 5)]}

    def diffuse(name: str, rgb: tuple[float, float, float], **extra: object) -> dict:
        m = {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*rgb, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
        }
        m.update(extra)  # type: ignore[arg-type]
        return m

    materials = [
        diffuse("floor", (1.0, 1.0, 1.0)),
        diffuse("white", (0.8, 0.8, 0.8)),
        diffuse("red", (0.8, 0.1, 0.1)),
        diffuse("green", (0.1, 0.8, 0.1)),
        diffuse(
            "panel",
            (0.8, 0.8, 0.8),
            emissiveFactor=list(_PANEL_FACTOR),
            extensions={"KHR_materials_emissive_strength": {"emissiveStrength": _PANEL_STRENGTH}},
        ),
        diffuse("box", (0.7, 0.7, 0.7)),
    ]
    materials[0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
    header = {
        "asset": {"version": "2.0", "generator": "probegrid.jobs.samples"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_emissive_strength"],
        "extensions": {
            "KHR_lights_punctual": {
                "lights": [
                    {
                        "name": "Lamp",
                        "type": "point",
                        "color": list(_LAMP_COLOR),
                        "intensity": LAMP_INTENSITY,
                        "range": _LAMP_RANGE,
                    }
                ]
            }
        },
        "scene": 0,
        "scenes": [{"name": "SampleRoom", "nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"name": "Room", "mesh": 0},
            {"name": "Panel", "mesh": 1},
            {"name": "Furniture", "translation": [0.0, 0.0, -0.2], "children": [4, 5]},
            {
                "name": "Lamp",
                "translation": list(LAMP_POSITION),
                "extensions": {"KHR_lights_punctual": {"light": 0}},
            },
            {
                "name": "TallBox",
                "mesh": 2,
                "translation": [-0.9, 0.6, -0.6],
                "rotation": _quat_y(20.0),
                "scale": [0.6, 1.2, 0.6],
            },
            {
                "name": "ShortBox",
                "mesh": 2,
                "translation": [0.9, 0.25, 0.5],
                "rotation": _quat_y(-15.0),
                "scale": [0.8, 0.5, 0.8],
            },
        ],
        "meshes": [room_mesh, panel_mesh, box_mesh_json],
        "materials": materials,
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "images": [{"name": "checker", "bufferView": png, "mimeType": "image/png"}],
        "accessors": w.accessors,
        "bufferViews": w.views,
        "buffers": [{"byteLength": len(w.blob)}],
    }
    js = json.dumps(header, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary = bytes(w.blob) + b"\x00" * (-len(w.blob) % 4)
    body = (
        struct.pack("<I", len(js))
        + b"JSON"
        + js
        + struct.pack("<I", len(binary))
        + b"BIN\x00"
        + binary
    )
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def sample_room_gltf(path: str | Path) -> Path:
    """Write the sample room as a .glb file; returns its path."""
    out = Path(path)
    if out.suffix.lower() != ".glb":
        raise ValueError(f"the sample room is written as .glb, got {out.name!r}.")
    out.write_bytes(sample_room_glb_bytes())
    return out


def write_sample_data(directory: str | Path) -> list[Path]:
    """Write ``sample_room.glb`` and ``sample_sky.hdr`` into ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    return [sample_room_gltf(d / "sample_room.glb"), write_sample_sky(d / "sample_sky.hdr")]


def main(argv: list[str] | None = None) -> int:
    """``python -m probegrid.jobs.samples [DIR]``: regenerate the sample data (default ``data/``)."""
    args = sys.argv[1:] if argv is None else argv
    target = Path(args[0]) if args else Path(__file__).resolve().parents[2] / "data"
    for p in write_sample_data(target):
        print(f"wrote {p} ({p.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
