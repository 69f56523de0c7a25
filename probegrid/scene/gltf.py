"""The glTF 2.0 loader (:func:`load_gltf`): the one module of the project that imports trimesh.

trimesh parses the meshes; materials, lights, node transforms, buffers and extensions are read
from the glTF JSON here (trimesh stores ``baseColorFactor`` as 8-bit, losing precision), and every
mesh instance becomes world-space triangles of a :class:`~probegrid.scene.model.Scene`.

Conventions
-----------
* World frame: glTF's, kept as is -- right-handed, +Y up, -Z forward, in the file's units (glTF
  says metres; ``CornellBox.glb`` is in millimetres and is *not* rescaled).
* A mesh instanced under a node whose world matrix has a negative determinant is re-wound
  (glTF 2.0 spec, "Transformations": a negative determinant makes the winding clockwise), so the
  scene's winding rule holds for every triangle.
* UVs are glTF's: ``(0, 0)`` is the upper-left corner of the image, ``v`` grows downward. trimesh
  flips ``v`` on load ("origin lower-left"); :func:`load_gltf` flips it back.
* Colours are linear Rec.709 RGB. ``baseColorTexture`` and ``emissiveTexture`` are sRGB-encoded
  (glTF spec, "Metallic-Roughness Material") and are decoded to linear once on load with the
  exact sRGB EOTF (IEC 61966-2-1); alpha stays linear. Textures are filtered bilinearly in
  linear space, wrapping as the texture's sampler says (default REPEAT), like a GPU with an
  sRGB texture format. A texture over the pixel limit is refused from its header; one larger
  than the bake resolves is area-averaged down on load, its mean kept
  (:mod:`probegrid.scene.texels`: 2^27 pixels, 1024 texels a side by default).
* Shading albedo = ``baseColorFactor.rgb * baseColorTexture.rgb * COLOR_0.rgb`` (glTF: COLOR_0
  "acts as an additional linear multiplier to base color"). Emission (radiance, cd/m^2 in the
  photometric reading of :mod:`probegrid.core.lights`) = ``emissiveFactor *
  KHR_materials_emissive_strength.emissiveStrength * emissiveTexture.rgb``.
* Lights (``KHR_lights_punctual``): position = the node's world translation, direction = the
  node's world matrix applied to -Z (normalised); point/spot intensity in candela, directional in
  lux, ``range`` kept; see :mod:`probegrid.core.lights` for units and falloff.

* Each texture reads its ``texCoord`` set through its ``KHR_texture_transform`` (offset,
  rotation, scale, and the transform's ``texCoord`` override), :class:`TexCoord`.
* What stops a ray: ``alphaMode`` (``MASK`` with ``alphaCutoff``, ``BLEND`` as stochastic
  coverage) and ``KHR_materials_transmission`` (thin: ``transmissionFactor`` times
  ``transmissionTexture``'s R, linear, read through its own ``texCoord`` and transform; the
  light through tinted by the base colour), see :mod:`probegrid.scene.coverage`.
* Geometry: ``KHR_mesh_quantization``, normalized and sparse accessors,
  ``EXT_meshopt_compression`` and ``KHR_draco_mesh_compression`` are decoded into plain
  arrays first (:mod:`probegrid.scene.accessors`); images: ``EXT_texture_webp`` is read (Pillow
  decodes WebP), ``KHR_texture_basisu`` through the fallback image its texture names (a KTX2
  texture without one is refused, or dropped with ``--ignore-extension KHR_texture_basisu``).
* ``EXT_mesh_gpu_instancing``: each instance (``TRANSLATION``, ``ROTATION``, ``SCALE``)
  places its node's mesh, in the node's frame.
* The default scene (``scene``, else the first) of a file with several is loaded.

Not honoured, and named in :attr:`Scene.unhonoured` (the bake prints them and the store's
manifest keeps them): metallic-roughness (every surface is Lambertian), normal and occlusion
textures, the material extensions of other lobes (sheen, clearcoat,
specular, anisotropy, iridescence, volume, ior, dispersion, diffuse transmission...),
and any other extension a file uses; morph targets and skins
(the bind pose is used), points and lines (skipped). A file whose ``extensionsRequired`` names
an extension outside :data:`HONOURED_EXTENSIONS` is refused, as the glTF specification asks of
a loader, with the option that loads it anyway with the extension ignored
(``ignore_extensions``, the CLI's ``--ignore-extension NAME``).

Files: a ``.gltf``'s buffers and images are read only from its own folder (and from folders
given with ``allow_paths``, the CLI's ``--allow-path``): each URI is checked before anything is
read (absolute paths, URLs and relative paths that lead outside, links resolved, are refused
without saying anything of the file), read once, and handed to trimesh from memory.

References: glTF 2.0 specification (Khronos, 2021); KHR_lights_punctual,
KHR_materials_emissive_strength, KHR_texture_transform, KHR_materials_transmission,
KHR_mesh_quantization, EXT_meshopt_compression, KHR_draco_mesh_compression, EXT_texture_webp
and KHR_texture_basisu extension specifications; IEC 61966-2-1 (sRGB).
"""

from __future__ import annotations

import base64
import copy
import io
import json
import math
import os
import re
import signal
import struct
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Final
from urllib.parse import unquote

import numpy as np
from numpy.typing import NDArray

from probegrid.core.lights import DirectionalLight, Light, PointLight, SpotLight
from probegrid.scene.accessors import DECODED_URI, float_accessor, plain_geometry, view_bytes
from probegrid.scene.model import Material, Scene, SceneError
from probegrid.scene.texels import TextureLimits, decode_texture, texture_limits
from probegrid.scene.textures import TexCoord, texture_transform

__all__ = ['HONOURED_EXTENSIONS', 'check_scene_file', 'gltf_mesh_count', 'load_gltf',
           'unhonoured_features']


#: glTF sampler wrap codes (OpenGL enums) -> our names.
_GL_WRAP: Final[dict[int, str]] = {10497: "repeat", 33071: "clamp", 33648: "mirror"}


#: Extensions the loader honours (module docstring); a file may list them in
#: ``extensionsRequired`` (glTF: refuse files needing others).
HONOURED_EXTENSIONS: Final[frozenset[str]] = frozenset({
    "KHR_lights_punctual", "KHR_materials_emissive_strength", "KHR_texture_transform",
    "KHR_materials_transmission", "KHR_mesh_quantization", "EXT_meshopt_compression",
    "KHR_draco_mesh_compression", "EXT_texture_webp", "KHR_texture_basisu",
    "EXT_mesh_gpu_instancing",
})

#: What an extension of another lobe or feature would change, for the list of what is not
#: honoured (any other extension is named as it is).
_NOT_HONOURED_NOTES: Final[dict[str, str]] = {
    "KHR_materials_pbrSpecularGlossiness": "specular-glossiness (read as base colour only)",
    "KHR_materials_unlit": "unlit (shaded as Lambertian)",
    "KHR_materials_variants": "variants (the default materials are used)",
}


#: Prefix given to material names before trimesh sees the file, to map its materials back.
_TAG: Final[str] = "__probegrid_material_"


_GLB_MAGIC: Final[bytes] = b"glTF"


_CHUNK_JSON: Final[int] = 0x4E4F534A


_CHUNK_BIN: Final[int] = 0x004E4942


def _glb_length(head: bytes, size: int, name: str) -> int:
    """The length a binary glTF's 12-byte header ``head`` declares, checked against the file's
    ``size`` (magic, version 2, not truncated)."""
    if len(head) < 12 or head[:4] != _GLB_MAGIC:
        raise SceneError(f"{name} is not a binary glTF file (bad magic).")
    version, length = struct.unpack_from("<II", head, 4)
    if version != 2:
        raise SceneError(f"{name} is binary glTF version {version}; only version 2 is supported.")
    if length > size:
        raise SceneError(f"{name} is truncated: header says {length} bytes, file has {size}.")
    return int(length)


def _parse_glb(data: bytes, name: str) -> tuple[dict, bytes | None]:
    """(JSON header, BIN chunk or None) of a binary glTF; checks the container's lengths."""
    length = _glb_length(data[:12], len(data), name)
    header, binary, offset = None, None, 12
    while offset < length:
        if offset + 8 > length:
            raise SceneError(f"{name} is truncated inside a chunk header at byte {offset}.")
        chunk_len, chunk_type = struct.unpack_from("<II", data, offset)
        start, end = offset + 8, offset + 8 + chunk_len
        if end > length:
            raise SceneError(f"{name} is truncated: a chunk runs past the end of the file.")
        if header is None:
            if chunk_type != _CHUNK_JSON:
                raise SceneError(f"{name}: the first chunk of a .glb must be JSON.")
            try:
                header = json.loads(data[start:end].decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise SceneError(f"{name} has an unreadable JSON chunk ({exc}).") from None
        elif chunk_type == _CHUNK_BIN and binary is None:
            binary = data[start:end]
        offset = end
    if not isinstance(header, dict):
        raise SceneError(f"{name} has no JSON chunk.")
    return header, binary


def _build_glb(header: dict, binary: bytes | None) -> bytes:
    """A binary glTF container (spec section "Binary glTF Layout")."""
    js = json.dumps(header, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    if binary is not None:
        b = binary + b"\x00" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(b), _CHUNK_BIN) + b
    return _GLB_MAGIC + struct.pack("<II", 2, 12 + len(chunks)) + chunks


#: A URI that names a scheme (``file:``, ``http:``) or a Windows drive (``C:``).
_SCHEME_RE: Final = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def _inside(target: Path, roots: Sequence[Path]) -> bool:
    """Whether ``target``, its links resolved, lies under one of ``roots`` (resolved too)."""
    real = os.path.realpath(target)
    for root in roots:
        top = os.path.realpath(root)
        if real == top or real.startswith(top.rstrip(os.sep) + os.sep):
            return True
    return False


def _uri_path(uri: str, base: Path, allow: Sequence[Path], what: str) -> Path:
    """The file a relative glTF URI names, after checking, before anything is read, that it is
    under the scene's folder ``base`` or one of the ``allow``-ed folders (links resolved);
    SceneError otherwise (no size, no content, nothing read)."""
    raw = unquote(uri)
    if not raw or raw.startswith(("/", "\\")) or _SCHEME_RE.match(raw) or "\0" in raw:
        raise SceneError(f"{what} is not a path relative to the scene's folder; only files "
                         "under it (or under a folder given with --allow-path) are read.")
    target = base / raw
    if not _inside(target, [base, *allow]):
        raise SceneError(f"{what} is outside the scene's folder; to read files under another "
                         "folder, name it with --allow-path DIR (load_gltf: allow_paths).")
    return target


def _uri_bytes(uri: str, base: Path, what: str, allow: Sequence[Path] = ()) -> bytes:
    """Bytes of a glTF URI: a data URI or a path relative to the .gltf file, confined to its
    folder and the ``allow``-ed ones (:func:`_uri_path`)."""
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1], validate=False)
        except (IndexError, ValueError) as exc:
            raise SceneError(f"{what} has a malformed data URI ({exc}).") from None
    target = _uri_path(uri, base, allow, what)
    if not target.is_file():
        raise SceneError(f"{what} not found: {target}")
    try:
        return target.read_bytes()
    except OSError as exc:
        raise SceneError(f"{what} cannot be read ({exc.strerror}).") from None


def _check_nodes(header: dict, name: str) -> None:
    """The node hierarchy must be a forest (glTF 2.0, 3.5.3): valid child indices, at most one
    parent per node, no cycles."""
    nodes = header.get("nodes", [])
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        for c in node.get("children", []):
            if not isinstance(c, int) or not 0 <= c < len(nodes):
                raise SceneError(f"{name}: node {i} has a child {c!r} that is not a node index.")
            if c in parent or c == i:
                raise SceneError(f"{name}: node {c} has more than one parent or is its own child "
                                 "(the node hierarchy must be a tree).")
            parent[c] = i
    for start in range(len(nodes)):  # walk up from every node: a cycle never reaches a root
        seen, n = set(), start
        while n in parent:
            if n in seen:
                raise SceneError(f"{name}: the node hierarchy has a cycle through node {n}.")
            seen.add(n)
            n = parent[n]


def _check_buffers(header: dict, binary: bytes | None, base: Path, name: str,
                   allow: Sequence[Path] = (), files: dict[str, bytes] | None = None
                   ) -> list[bytes]:
    """Every buffer exists and holds its declared byteLength (catches truncated files); the
    external files read are kept in ``files`` by URI. Returns each buffer's bytes (empty for an
    ``EXT_meshopt_compression`` fallback buffer without data: it is never read)."""
    out = []
    for i, buf in enumerate(header.get("buffers", [])):
        need = int(buf.get("byteLength", 0))
        if "uri" in buf:
            uri = str(buf["uri"])
            data = _uri_bytes(uri, base, f"{name}: buffer {i} ({uri[:80]})", allow)
            if files is not None and not uri.startswith("data:"):
                files[uri] = data
        elif i == 0 and binary is not None:
            data = binary
        elif buf.get("extensions", {}).get("EXT_meshopt_compression", {}).get("fallback"):
            out.append(b"")
            continue
        else:
            raise SceneError(f"{name}: buffer {i} has no data (no uri and no .glb BIN chunk).")
        if len(data) < need:
            raise SceneError(f"{name}: buffer {i} is truncated (shorter than its byteLength "
                             f"{need}).")
        out.append(data)
    return out


def _node_world_matrices(header: dict, name: str) -> dict[int, NDArray[np.float64]]:
    """World matrix (4x4, column vectors) of every node reachable from the default scene."""
    nodes = header.get("nodes", [])
    scenes = header.get("scenes", [])
    if not scenes:
        return {}
    roots = scenes[int(header.get("scene", 0))].get("nodes", [])
    world: dict[int, NDArray[np.float64]] = {}
    stack = [(int(r), np.eye(4)) for r in roots]
    while stack:  # loop over scene-graph nodes (not rays or pixels)
        i, parent = stack.pop()
        if i in world or not 0 <= i < len(nodes):
            raise SceneError(f"{name}: node {i} is out of range or reached twice (not a tree).")
        node = nodes[i]
        if "matrix" in node:
            local = np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
        else:
            t = np.array(node.get("translation", [0, 0, 0]), dtype=np.float64)
            x, y, z, w = np.array(node.get("rotation", [0, 0, 0, 1]), dtype=np.float64)
            s = np.array(node.get("scale", [1, 1, 1]), dtype=np.float64)
            rot = np.array(
                [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
                ]
            )
            local = np.eye(4)
            local[:3, :3] = rot * s[None, :]
            local[:3, 3] = t
        if not np.all(np.isfinite(local)):
            raise SceneError(f"{name}: node {i} has a non-finite transform.")
        world[i] = parent @ local
        stack.extend((int(c), world[i]) for c in node.get("children", []))
    return world


def _parse_lights(header: dict, name: str) -> tuple[Light, ...]:
    """KHR_lights_punctual lights placed by the default scene's nodes, in node order."""
    defs = header.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
    if not defs:
        return ()
    world = _node_world_matrices(header, name)
    lights: list[Light] = []
    for i in sorted(world):
        ext = header["nodes"][i].get("extensions", {}).get("KHR_lights_punctual")
        if ext is None:
            continue
        k = int(ext["light"])
        if not 0 <= k < len(defs):
            raise SceneError(f"{name}: node {i} refers to missing light {k}.")
        d = defs[k]
        m = world[i]
        position = m[:3, 3]
        direction = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
        color = d.get("color", [1.0, 1.0, 1.0])
        intensity = d.get("intensity", 1.0)
        kind = d.get("type")
        try:
            if kind == "point":
                lights.append(PointLight(position, color, intensity, range=d.get("range")))
            elif kind == "spot":
                spot = d.get("spot", {})
                lights.append(
                    SpotLight(
                        position,
                        direction,
                        color,
                        intensity,
                        range=d.get("range"),
                        inner_cone_angle=spot.get("innerConeAngle", 0.0),
                        outer_cone_angle=spot.get("outerConeAngle", math.pi / 4),
                    )
                )
            elif kind == "directional":
                lights.append(DirectionalLight(direction, color, intensity))
            else:
                raise SceneError(
                    f"{name}: light {k} has type {kind!r}; expected point, spot or directional."
                )
        except SceneError:
            raise
        except (ValueError, TypeError) as exc:
            raise SceneError(f"{name}: light {k} ({kind}) is invalid: {exc}") from None
    return tuple(lights)


def _texture_array(image: object, channels: int, what: str) -> NDArray[np.float32]:
    """A PIL image (as trimesh opened it) -> (H, W, channels) float32 linear RGB(A), within
    the current texture limits (:mod:`probegrid.scene.texels`)."""
    return decode_texture(image, channels, what)


def _texture_source(tex: dict) -> int | None:
    """The image a texture reads: ``EXT_texture_webp``'s source first (Pillow decodes WebP),
    else ``source`` (for ``KHR_texture_basisu``, the fallback image)."""
    webp = tex.get("extensions", {}).get("EXT_texture_webp", {}).get("source")
    return int(webp) if webp is not None else tex.get("source")


def _texture_info(
    header: dict, info: dict | None, mat_name: str, slot: str, ignore: frozenset[str] = frozenset()
) -> tuple[str, tuple[str, str], TexCoord] | None:
    """(image description, wrap modes, texture coordinates) of a textureInfo, after validating
    what we support; None for no texture (or a KTX2-only one, ``KHR_texture_basisu`` ignored)."""
    if info is None:
        return None
    try:
        tex = header["textures"][int(info["index"])]
        sampler = header.get("samplers", [])[tex["sampler"]] if "sampler" in tex else {}
        source = _texture_source(tex)
        if source is None and "KHR_texture_basisu" in tex.get("extensions", {}):
            if "KHR_texture_basisu" in ignore:
                return None
            raise SceneError(
                f"material {mat_name!r}: {slot} is a KTX2 (KHR_texture_basisu) image without a "
                "fallback, which probegrid cannot decode; --ignore-extension KHR_texture_basisu "
                "bakes it with the texture left out.")
        image = header["images"][source] if source is not None else {}
    except (KeyError, IndexError, TypeError):
        raise SceneError(f"material {mat_name!r}: {slot} refers to a missing texture.") from None
    desc = image.get("uri", f"bufferView {image.get('bufferView')}")
    if isinstance(desc, str) and desc.startswith("data:"):
        desc = "embedded data URI"
    wrap = tuple(_GL_WRAP.get(int(sampler.get(k, 10497)), "repeat") for k in ("wrapS", "wrapT"))
    transform = info.get("extensions", {}).get("KHR_texture_transform")
    index = info.get("texCoord", 0)
    try:
        if transform is None:
            tc = texture_transform(index=index)
        else:
            tc = texture_transform(transform.get("offset", (0.0, 0.0)),
                                   transform.get("rotation", 0.0),
                                   transform.get("scale", (1.0, 1.0)),
                                   index=transform.get("texCoord", index))
    except ValueError as exc:
        raise SceneError(f"material {mat_name!r}: {slot}: {exc}") from None
    return (f"{slot} of material {mat_name!r} (image {desc})", wrap,  # type: ignore[return-value]
            tc)


def _material_from_json(header: dict, index: int, tm_material: object | None,
                        ignore: frozenset[str] = frozenset(),
                        image_of: Callable[[int], object] | None = None) -> Material:
    """Material ``index`` of the glTF JSON; texture pixels come from trimesh's decoded images,
    the transmission texture's (which trimesh does not keep) from ``image_of(source)``, a
    Pillow image of the file's image ``source``."""
    mj = header["materials"][index]
    mname = str(mj.get("name", f"#{index}"))
    pbr = mj.get("pbrMetallicRoughness", {})
    ext = mj.get("extensions", {})
    strength = ext.get("KHR_materials_emissive_strength", {})
    emissive = np.array(mj.get("emissiveFactor", [0.0, 0.0, 0.0]), dtype=np.float64)
    emissive = emissive * float(strength.get("emissiveStrength", 1.0))
    tx = ext.get("KHR_materials_transmission", {})
    transmission = float(tx.get("transmissionFactor", 0.0))
    tx_texture, tx_wrap, tx_uv = None, ("repeat", "repeat"), TexCoord()
    found = (_texture_info(header, tx.get("transmissionTexture"), mname, "transmissionTexture",
                           ignore) if transmission > 0 else None)
    if found is not None and image_of is not None:
        what, tx_wrap, tx_uv = found
        source = _texture_source(header["textures"][int(tx["transmissionTexture"]["index"])])
        if source is not None:  # (R: linear data, not colour)
            tx_texture = np.ascontiguousarray(decode_texture(
                image_of(int(source)), 3, what, linear=True)[..., :1])
    alpha_mode = str(mj.get("alphaMode", "OPAQUE"))
    alpha_cutoff = float(mj.get("alphaCutoff", 0.5))
    textures: dict[str, NDArray[np.float32] | None] = {}
    wraps: dict[str, tuple[str, str]] = {}
    coords: dict[str, TexCoord] = {}
    for slot, info, attr, channels in (
        ("baseColorTexture", pbr.get("baseColorTexture"), "baseColorTexture", 4),
        ("emissiveTexture", mj.get("emissiveTexture"), "emissiveTexture", 3),
    ):
        found = _texture_info(header, info, mname, slot, ignore)
        textures[slot] = None
        wraps[slot] = ("repeat", "repeat")
        coords[slot] = TexCoord()
        if found is None or tm_material is None:
            continue
        what, wraps[slot], coords[slot] = found
        image = getattr(tm_material, attr, None)
        if image is None:
            raise SceneError(f"{what} is missing or could not be decoded.")
        if slot == "baseColorTexture" and alpha_mode == "MASK":
            # a cut-out's alpha is thresholded per source texel before any reduction: a
            # reduced texture's alpha is then the share of its footprint that stops rays,
            # which BLEND's stochastic coverage honours on average (a re-threshold would not)
            factor_a = float(pbr.get("baseColorFactor", [1.0] * 4)[3])
            cutoff = alpha_cutoff / factor_a if factor_a > 0 else np.inf
            textures[slot] = decode_texture(image, channels, what, alpha_cutoff=cutoff)
            if textures[slot].shape[:2] != tuple(int(v) for v in image.size)[::-1]:
                alpha_mode, alpha_cutoff = "BLEND", 0.5
                if factor_a > 0:  # (the factor multiplies it back: the share stopped)
                    np.minimum(textures[slot][..., 3] / factor_a, 1.0,
                               out=textures[slot][..., 3])
            continue
        textures[slot] = _texture_array(image, channels, what)
    try:
        return Material(
            base_color=pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]),
            base_color_texture=textures["baseColorTexture"],
            emissive=emissive,
            emissive_texture=textures["emissiveTexture"],
            double_sided=bool(mj.get("doubleSided", False)),
            name=mname,
            base_color_wrap=wraps["baseColorTexture"],  # type: ignore[arg-type]
            emissive_wrap=wraps["emissiveTexture"],  # type: ignore[arg-type]
            alpha_mode=alpha_mode,
            alpha_cutoff=alpha_cutoff,
            transmission=transmission,
            base_color_uv=coords["baseColorTexture"],
            emissive_uv=coords["emissiveTexture"],
            transmission_texture=tx_texture,
            transmission_wrap=tx_wrap,  # type: ignore[arg-type]
            transmission_uv=tx_uv,
        )
    except ValueError as exc:
        raise SceneError(f"material {mname!r} is invalid: {exc}") from None


def _vertex_colors(raw: NDArray) -> NDArray[np.float64]:
    """COLOR_0 accessor data -> (V, 4) float64; integer types are normalized (glTF spec)."""
    a = np.asarray(raw)
    if np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    a = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    if a.shape[1] == 3:
        a = np.concatenate([a, np.ones((len(a), 1))], axis=1)
    return a[:, :4]


def load_gltf(path: str | Path, *, allow_paths: Sequence[str | os.PathLike[str]] = (),
              ignore_extensions: Sequence[str] = (),
              textures: TextureLimits | None = None) -> Scene:
    """Load a glTF 2.0 scene (.gltf or .glb) into world space.

    trimesh reads the meshes, the node hierarchy and the images; factors, samplers, the
    emissive-strength extension and ``KHR_lights_punctual`` (which trimesh ignores) are read
    from the glTF JSON (trimesh stores ``baseColorFactor`` as 8-bit, losing precision). Every
    primitive of every mesh node of the default scene becomes triangles in world space; points
    and lines are skipped. Primitives without a material get glTF's default material.

    Parameters
    ----------
    path : str or Path
        A ``.gltf`` (with its buffers and images beside it, or embedded as data URIs) or ``.glb``.
    allow_paths : sequence of path
        Folders other than the scene's own whose files its URIs may name (the CLI's
        ``--allow-path``). A URI is checked before anything is read: an absolute path, a URL or
        a relative path that leads (links resolved) outside the scene's folder and these is a
        :class:`SceneError`.
    ignore_extensions : sequence of str
        Extensions a file may require that the loader does not honour, loaded with them
        ignored (the CLI's ``--ignore-extension``; ``"*"``: all); they are named in
        :attr:`Scene.unhonoured`.
    textures : TextureLimits, optional
        The most pixels a texture image may have and the longest side textures are reduced
        to (area-averaged, the mean kept; :mod:`probegrid.scene.texels`); default 2^27 and
        1024.

    Returns
    -------
    Scene

    Raises
    ------
    SceneError
        Missing or unreadable file, truncated .glb or buffer, missing or undecodable texture,
        non-finite vertices, no triangles, unsupported features (see module docstring).
    """
    p = check_scene_file(path)
    label = p.name
    data = p.read_bytes()
    try:
        with texture_limits(textures or TextureLimits()):
            return _load_gltf_data(p, data, [Path(a) for a in allow_paths],
                                   frozenset(str(e) for e in ignore_extensions))
    except SceneError:
        raise
    except (AttributeError, TypeError, KeyError, IndexError, ValueError, RecursionError) as exc:
        # JSON of the wrong shape ("asset": "2.0", "materials": [5], a node cycle, ...)
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SceneError(f"{label} is not a well-formed glTF 2.0 scene ({msg}).") from None


def check_scene_file(path: str | Path) -> Path:
    """The checks of :func:`load_gltf` that read no more than a header: a ``.gltf`` or ``.glb``
    that exists, and a ``.glb``'s header (:func:`_glb_length`; what a caller can refuse before
    starting any work). Raises :class:`SceneError`; returns the path."""
    p = Path(path)
    if p.suffix.lower() not in (".gltf", ".glb"):
        raise SceneError(f"{p.name}: expected a .gltf or .glb file, got suffix {p.suffix!r}.")
    if not p.is_file():
        raise SceneError(f"scene file not found: {p}")
    if p.suffix.lower() == ".glb":
        try:
            with open(p, "rb") as f:
                head = f.read(12)
            size = p.stat().st_size
        except OSError as exc:
            raise SceneError(f"cannot read {p}: {exc.strerror or exc}") from None
        _glb_length(head, size, p.name)
    return p


def gltf_mesh_count(path: str | Path) -> int | None:
    """Number of meshes a glTF file's document declares (None when it cannot be read)."""
    p = Path(path)
    try:
        data = p.read_bytes()
        doc = (_parse_glb(data, p.name)[0] if data[:4] == _GLB_MAGIC
               else json.loads(data.decode("utf-8")))
    except (OSError, SceneError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    meshes = doc.get("meshes") if isinstance(doc, dict) else None
    return len(meshes) if isinstance(meshes, list) else 0


#: Most instances ``EXT_mesh_gpu_instancing`` may place in one file (each is a copy of its
#: mesh's triangles in the scene).
MAX_INSTANCES: Final[int] = 1 << 20
#: Most triangles the instances of a file may add.
MAX_INSTANCED_TRIANGLES: Final[int] = 1 << 26

_INSTANCING: Final[str] = "EXT_mesh_gpu_instancing"


def _mesh_triangles(header: dict, mesh: object) -> int:
    """About how many triangles mesh ``mesh`` holds (its index or position counts / 3), from
    the JSON alone; 0 for what is not a mesh (the reader refuses it later)."""
    meshes, accs = header.get("meshes", []), header.get("accessors", [])
    if not isinstance(mesh, int) or not 0 <= mesh < len(meshes):
        return 0
    total = 0
    for prim in meshes[mesh].get("primitives", []):
        a = prim.get("indices", prim.get("attributes", {}).get("POSITION"))
        if isinstance(a, int) and 0 <= a < len(accs):
            total += int(accs[a].get("count", 0)) // 3
    return total


def _expand_instances(tagged: dict, header: dict, buffers: Sequence[bytes], label: str) -> None:
    """``EXT_mesh_gpu_instancing`` made plain, in ``tagged`` (a copy of ``header``): the mesh
    of a node with instances moves to one new child node per instance, whose ``translation``,
    ``rotation`` (a unit quaternion, normalized integers allowed) and ``scale`` are the
    instance's (the extension: an instance's transform applies in the node's frame, before the
    node's own, as a child's does). Attributes other than these three (``_ID`` and the like)
    are not read."""
    nodes = tagged.get("nodes", [])
    placed = triangles = 0
    for i, node in enumerate(header.get("nodes", [])):
        ext = node.get("extensions", {}).get(_INSTANCING)
        if ext is None or "mesh" not in node:
            continue
        attrs = ext.get("attributes", {})
        what = f"{label}: node {i}'s {_INSTANCING}"
        cols: dict[str, NDArray[np.float64]] = {}
        for name, width in (("TRANSLATION", 3), ("ROTATION", 4), ("SCALE", 3)):
            if name in attrs:
                a = float_accessor(header, buffers, attrs[name], what)
                if a.shape[1] != width or not np.all(np.isfinite(a)):
                    raise SceneError(f"{what} {name} must be finite VEC{width}, got "
                                     f"{a.shape[1]} components per instance.")
                cols[name] = a
        if not cols:
            raise SceneError(f"{what} has none of TRANSLATION, ROTATION, SCALE.")
        counts = {len(a) for a in cols.values()}
        if len(counts) != 1:
            raise SceneError(f"{what} attributes have different counts "
                             f"({', '.join(f'{k} {len(a)}' for k, a in cols.items())}).")
        n = counts.pop()
        placed += n
        triangles += n * _mesh_triangles(header, node["mesh"])
        if placed > MAX_INSTANCES or triangles > MAX_INSTANCED_TRIANGLES:
            raise SceneError(f"{label}: {_INSTANCING} places over {MAX_INSTANCES} instances or "
                             f"{MAX_INSTANCED_TRIANGLES} triangles; bake fewer.")
        if "ROTATION" in cols:
            q = cols["ROTATION"]
            norm = np.linalg.norm(q, axis=1, keepdims=True)
            if np.any(norm == 0):
                raise SceneError(f"{what} ROTATION has a zero quaternion.")
            cols["ROTATION"] = q / norm
        first = len(nodes)
        for k in range(n):  # loop over instances (scene-graph nodes, not rays or pixels)
            child = {"mesh": node["mesh"], "name": f"{node.get('name', i)}#instance{k}"}
            for name, key in (("TRANSLATION", "translation"), ("ROTATION", "rotation"),
                              ("SCALE", "scale")):
                if name in cols:
                    child[key] = [float(x) for x in cols[name][k]]
            nodes.append(child)
        target = tagged["nodes"][i]
        target.pop("mesh")
        target.get("extensions", {}).pop(_INSTANCING, None)
        target["children"] = list(target.get("children", [])) + list(range(first, first + n))


def _required(header: dict, label: str, ignore: frozenset[str]) -> None:
    """Refuse a file that requires an extension the loader does not honour (and that
    ``ignore`` does not name), with the option that loads it anyway."""
    required = header.get("extensionsRequired", [])
    refused = sorted(set(required) - HONOURED_EXTENSIONS - ignore) if "*" not in ignore else []
    if refused:
        names = ", ".join(refused)
        opts = " ".join(f"--ignore-extension {e}" for e in refused)
        raise SceneError(f"{label} requires the glTF extension{'s' if len(refused) > 1 else ''} "
                         f"{names}, which probegrid does not honour; {opts} bakes it with "
                         f"{'them' if len(refused) > 1 else 'it'} ignored.")


def unhonoured_features(header: dict) -> tuple[str, ...]:
    """What a glTF document uses that the bake does not honour (module docstring), each named
    once, in a fixed order."""
    found: list[str] = []
    mats = header.get("materials", [])
    if any(float(m.get("pbrMetallicRoughness", {}).get("metallicFactor", 1.0)) > 0
           or "metallicRoughnessTexture" in m.get("pbrMetallicRoughness", {}) for m in mats):
        found.append("metallic-roughness (every surface is Lambertian)")
    for key in ("normalTexture", "occlusionTexture"):
        if any(key in m for m in mats):
            found.append(key)
    used = set(header.get("extensionsUsed", [])) | set(header.get("extensionsRequired", []))
    for m in mats:
        used |= set(m.get("extensions", {}))
    for name in sorted(used - HONOURED_EXTENSIONS):
        found.append(f"{name}" + (f": {_NOT_HONOURED_NOTES[name]}" if name in _NOT_HONOURED_NOTES
                                  else ""))
    prims = [p for m in header.get("meshes", []) for p in m.get("primitives", [])]
    if header.get("skins"):
        found.append("skins (the bind pose is used)")
    if any(p.get("targets") for p in prims):
        found.append("morph targets (the base shape is used)")
    if any(int(p.get("mode", 4)) not in (4, 5, 6) for p in prims):
        found.append("points and lines (skipped)")
    return tuple(found)


def _texcoord_sets(header: dict, ignore: frozenset[str]) -> dict[int, int]:
    """The highest TEXCOORD set the base colour, emissive or transmission texture of each
    material reads (materials reading only the first are left out)."""
    top: dict[int, int] = {}
    for i, m in enumerate(header.get("materials", [])):
        for info in (m.get("pbrMetallicRoughness", {}).get("baseColorTexture"),
                     m.get("emissiveTexture"),
                     m.get("extensions", {}).get("KHR_materials_transmission", {}).get(
                         "transmissionTexture")):
            found = _texture_info(header, info, str(m.get("name", f"#{i}")), "texture", ignore)
            if found is not None and found[2].index > 0:
                top[i] = max(top.get(i, 0), found[2].index)
    return top


#: Prefix of the further TEXCOORD sets handed through trimesh as custom attributes.
_UV_TAG: Final[str] = "_PROBEGRID_TEXCOORD_"


def _load_gltf_data(p: Path, data: bytes, allow: Sequence[Path] = (),
                    ignore: frozenset[str] = frozenset()) -> Scene:
    """:func:`load_gltf` of the file's bytes (its errors of malformed JSON not yet caught)."""
    label, suffix = p.name, p.suffix.lower()
    if suffix == ".glb":
        header, binary = _parse_glb(data, label)
    else:
        binary = None
        try:
            header = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SceneError(f"{label} is not valid glTF JSON ({exc}).") from None
        if not isinstance(header, dict):
            raise SceneError(f"{label} is not a glTF JSON object.")
    version = str(header.get("asset", {}).get("version", ""))
    if not version.startswith("2."):
        raise SceneError(f"{label} is glTF version {version or '?'}; only 2.x is supported.")
    _required(header, label, ignore)
    files: dict[str, bytes] = {}  # the external files, read once, handed on to trimesh
    buffers = _check_buffers(header, binary, p.parent, label, allow, files)
    _check_nodes(header, label)
    for i, img in enumerate(header.get("images", [])):
        uri = str(img.get("uri", ""))
        if "uri" in img and not uri.startswith("data:"):
            files[uri] = _uri_bytes(uri, p.parent, f"{label}: image {i} ({uri[:80]})", allow)
    sets_of = _texcoord_sets(header, ignore)
    n_sets = max(sets_of.values(), default=0)

    # What trimesh reads: compressed, quantized and sparse geometry made plain first (then
    # handed over as a .gltf whose buffers are all in ``files``), the further TEXCOORD sets as
    # custom attributes, material names tagged so its materials map back to their indices.
    plain = plain_geometry(header, buffers, label)
    tagged = copy.deepcopy(header if plain is None else plain[0])
    as_glb = binary is not None or suffix == ".glb"
    if plain is not None:
        files[DECODED_URI] = plain[1]
        for i, buf in enumerate(tagged.get("buffers", [])):
            if "uri" not in buf:  # the .glb's BIN chunk, or a meshopt fallback never read
                buf["uri"] = f"probegrid-buffer-{i}.bin"
                files[buf["uri"]] = buffers[i] if i < len(buffers) else b""
                buf["byteLength"] = len(files[buf["uri"]])
        as_glb, binary = False, None
    _expand_instances(tagged, header, buffers, label)
    for i, m in enumerate(tagged.get("materials", [])):
        m["name"] = f"{_TAG}{i}"
    if n_sets:
        for mesh in tagged.get("meshes", []):
            for prim in mesh.get("primitives", []):
                attrs = prim.get("attributes", {})
                for k in range(1, n_sets + 1):
                    if f"TEXCOORD_{k}" in attrs:
                        attrs[f"{_UV_TAG}{k}"] = attrs[f"TEXCOORD_{k}"]
    tm_scene = _trimesh_load(tagged, binary, p, label, files, as_glb=as_glb)

    n_json_mats = len(header.get("materials", []))
    tm_materials: dict[int, object] = {}
    instances = []
    order = list(tm_scene.geometry.keys())
    for node in tm_scene.graph.nodes_geometry:
        matrix, geom_name = tm_scene.graph[node]
        geom = tm_scene.geometry[geom_name]
        if not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue  # points, lines
        instances.append((order.index(geom_name), np.asarray(matrix, np.float64).tobytes(), geom))
    instances.sort(key=lambda item: (item[0], item[1]))  # deterministic (graph order is not)

    verts, tris, mats, uvs, cols = [], [], [], [], []
    extra: list[list[NDArray[np.float64]]] = [[] for _ in range(n_sets)]
    any_uv = any_col = False
    count = 0
    for _, mbytes, geom in instances:
        m = np.frombuffer(mbytes, dtype=np.float64).reshape(4, 4)
        v = np.asarray(geom.vertices, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]
        f = np.asarray(geom.faces, dtype=np.int64)
        if np.linalg.det(m[:3, :3]) < 0:
            f = f[:, [0, 2, 1]]
        visual = geom.visual
        material = getattr(visual, "material", None)
        mname = getattr(material, "name", None)
        if isinstance(mname, str) and mname.startswith(_TAG):
            idx = int(mname[len(_TAG) :])
            tm_materials.setdefault(idx, material)
        else:
            idx = n_json_mats  # glTF default material
        uv = getattr(visual, "uv", None)
        if uv is not None and len(uv) == len(v):
            uv = np.asarray(uv, dtype=np.float64) * [1.0, -1.0] + [0.0, 1.0]  # undo trimesh flip
            any_uv = True
        else:
            uv = np.zeros((len(v), 2))
        attrs = getattr(visual, "vertex_attributes", {}) or {}
        col = attrs.get("color") if hasattr(attrs, "get") else None
        if col is not None and len(col) == len(v):
            col = _vertex_colors(col)
            any_col = True
        else:
            col = np.ones((len(v), 4))
        custom = getattr(geom, "vertex_attributes", {}) or {}
        for k in range(1, n_sets + 1):  # (not flipped: trimesh does not touch them)
            a = custom.get(f"{_UV_TAG}{k}") if hasattr(custom, "get") else None
            ok = a is not None and len(a) == len(v)
            if not ok and sets_of.get(idx, 0) >= k:
                raise SceneError(f"{label}: material "
                                 f"{header['materials'][idx].get('name', f'#{idx}')!r} has a "
                                 f"texture that reads TEXCOORD_{k}, which a primitive using it "
                                 "does not have.")
            extra[k - 1].append(np.asarray(a, np.float64).reshape(len(v), 2) if ok
                                else np.zeros((len(v), 2)))
        verts.append(v)
        tris.append(f + count)
        mats.append(np.full(len(f), idx, np.int64))
        uvs.append(uv)
        cols.append(col)
        count += len(v)
    if not tris:
        raise SceneError(f"{label} has no triangles in its default scene.")

    def image_of(source: int) -> object:
        import PIL.Image

        try:
            img = header["images"][source]
            if "uri" in img:
                uri = str(img["uri"])
                data = files[uri] if uri in files else _uri_bytes(
                    uri, p.parent, f"{label}: image {source}", allow)
            else:
                data = view_bytes(header, buffers, int(img["bufferView"]), label)
            return PIL.Image.open(io.BytesIO(data))
        except (KeyError, IndexError, TypeError, ValueError, OSError) as exc:
            raise SceneError(f"{label}: image {source} cannot be read "
                             f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})."
                             ) from None

    materials = [_material_from_json(header, i, tm_materials.get(i), ignore, image_of)
                 for i in range(n_json_mats)]
    material = np.concatenate(mats)
    if np.any(material == n_json_mats):
        materials.append(Material(name="glTF default"))
    return Scene(
        vertices=np.concatenate(verts),
        triangles=np.concatenate(tris),
        material=material,
        materials=tuple(materials),
        uvs=np.concatenate(uvs) if any_uv else None,
        colors=np.concatenate(cols) if any_col else None,
        lights=_parse_lights(header, label),
        name=label,
        extra_uvs=tuple(np.concatenate(e) for e in extra),
        unhonoured=unhonoured_features(header),
    )


def _trimesh_load(header: dict, binary: bytes | None, path: Path, label: str,
                  files: dict[str, bytes] | None = None, *, as_glb: bool | None = None):
    """trimesh.Scene of a (re-encoded) glTF; any trimesh failure becomes a SceneError.

    trimesh reads a ``.gltf``'s external files from ``files`` (URI -> bytes, read and checked
    by :func:`_uri_bytes`), never from the file system: its own resolver would fall back to a
    file of the same name elsewhere.

    trimesh's loader catches ``BaseException`` around format handlers, which would swallow a
    Ctrl-C (or the CLI's SIGTERM, turned into KeyboardInterrupt) arriving during the load; in
    the main thread, SIGINT and SIGTERM are held during the call and delivered to their own
    handlers right after it (loading takes a fraction of a second).
    """
    import trimesh

    glb = (binary is not None or path.suffix.lower() == ".glb") if as_glb is None else as_glb

    def load():
        if glb:
            return trimesh.load_scene(
                io.BytesIO(_build_glb(header, binary)), file_type="glb", process=False
            )
        resolver = _Files(dict(files or {}), label)
        return trimesh.load_scene(
            io.BytesIO(json.dumps(header).encode("utf-8")),
            file_type="gltf",
            resolver=resolver,
            process=False,
        )

    try:
        with _signals_held():
            return load()
    except SceneError:
        raise
    except Exception as exc:  # noqa: BLE001 -- trimesh raises arbitrary types on bad accessors
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SceneError(f"{label} could not be read by trimesh: {msg}") from None


class _Files(dict):
    """The external files of a glTF by URI, as trimesh's resolver: a URI not read and checked
    beforehand is a SceneError, never looked up on disk."""

    def __init__(self, files: dict[str, bytes], label: str) -> None:
        super().__init__(files)
        self._label = label

    def __missing__(self, uri: str) -> bytes:
        raise SceneError(f"{self._label}: {uri[:80]!r} is not a file the scene declares.")

    def get(self, name: str, default: object = None) -> bytes:  # type: ignore[override]
        return self[name]


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration, then deliver those that arrived to the
    handlers in place before (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.getsignal(sig) for sig in sigs}
    for sig in sigs:
        signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig in sigs:
            handler = previous[sig]
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)

