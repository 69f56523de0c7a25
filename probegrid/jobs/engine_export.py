"""``probegrid export STORE --target threejs|bevy|ktx2 --out DIR``: a probe grid store written as
files an engine loads as they are, each folder with a ``manifest.json`` naming its consumer and
conventions.

Targets (layouts and conventions in :mod:`probegrid.export.engines`):

``threejs``
    ``lightprobegrid.ktx2``: three.js' ``LightProbeGrid`` / ``LightProbeGridWebGL`` SH atlas, a
    3D RGBA texture (``R16G16B16A16_SFLOAT`` by default, or ``R32G32B32A32_SFLOAT``) of
    ``nx x ny x 7 (nz + 2)`` texels holding the store's deringed radiance SH (three.js clamps
    negative irradiance, so the raw projection's ringing would render black; ``sh="raw"`` on
    request); ``lightprobegrid.json`` the header (position, size, resolution, padding,
    packing, dtype, which SH).
``bevy``
    ``irradiance_volume.ktx2``: Bevy's ``IrradianceVolume`` 3D texture of ``nx x 2 ny x 3 nz``
    ambient cubes (``E5B9G9R9_UFLOAT_PACK32`` by default, as Bevy ships them, or RGBA16F /
    RGBA32F) holding the store's diffuse map (irradiance / pi) along +-X, +-Y, +-Z, and the
    ``Transform`` that places it in the manifest.
``ktx2``
    ``diffuse.ktx2`` (one level) and ``specular.ktx2`` (the GGX chain as mips, level ``k`` at
    roughness ``k / (levels - 1)``): cube-map arrays with one layer per probe in store order
    (``index = (i ny + j) nz + k``), or plain cube maps with ``probe=(i, j, k)``; ``sh.json``
    the radiance SH (deringed by default) and their consumer forms. Faces +X, -X, +Y, -Y, +Z,
    -Z in the OpenGL/KTX2 table (``cube_convention="gltf"``), or mirrored for three.js (x) or
    Bevy (z) so that their lookups read each world direction's light
    (:func:`probegrid.export.engines.mirror_cube`); ``RGBA16F`` by default.
``filament``
    One probe (``probe=(i, j, k)``: Filament's ``IndirectLight`` is one environment) as the
    KTX1 files ``probegrid filter --format filament`` writes (:mod:`probegrid.export.filament`:
    ``environment_ibl.ktx`` with the SH in its ``sh`` key, ``environment_skybox.ktx``): the
    probe's stored incoming cube (a bake with ``--store-incoming``) filtered again at the
    roughness each mip has for Filament, ``r_k = 1 - sqrt(1 - k / (levels - 1))``, since the
    store's chain is at probegrid's ``r = k / (levels - 1)``; a face size of at least 32.

Invalid probes are filled from their valid neighbours first (the manifest says how many).
Everything is read and checked before the output directory is touched; the manifest is written
last (:func:`probegrid.jobs.filter.prepare_output_dir` semantics: a directory with a manifest
holds a finished export). KTX2 files can be Zstandard-supercompressed (``zstd=True``).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from probegrid._fs import atomic_write_json
from probegrid._types import CubeConvention, EngineTarget, SHKind, choices
from probegrid._version import __version__
from probegrid.core.conventions import conventions
from probegrid.export import engines, ktx2
from probegrid.jobs.export import SH_MEANING, _map_arrays, parse_probe, read_sh, sh_document
from probegrid.jobs.filter import prepare_output_dir
from probegrid.jobs.staging import listed_files, remove_stale
from probegrid.store import StoreError, open_store

__all__ = ["TARGETS", "export_grid"]

TARGETS: tuple[str, ...] = choices(EngineTarget)
_DEFAULT_FORMAT = {"threejs": 97, "bevy": 123, "ktx2": 97}
_ALLOWED_FORMATS = {"threejs": (97, 109), "bevy": (97, 109, 123), "ktx2": (97, 109, 123)}

_CONSUMERS = {
    "threejs": ("three.js LightProbeGrid / LightProbeGridWebGL (examples/jsm/lighting, r187): "
                "load lightprobegrid.ktx2 with KTX2Loader (a Data3DTexture, linear filtering), "
                "make new LightProbeGrid(size.x, size.y, size.z, nx, ny, nz) at position and set "
                "its texture"),
    "bevy": ("Bevy IrradianceVolume (bevy_pbr light_probe): a LightProbe entity with "
             "IrradianceVolume { voxels: irradiance_volume.ktx2, intensity } and the transform "
             "below"),
    "ktx2": ("any KTX2 loader: cube maps (arrays) in the OpenGL/Vulkan/KTX2 face table; the "
             "glTF Sample Viewer and Bevy's EnvironmentMapLight read the same face table as "
             "glTF-IBL-Sampler writes"),
    "filament": ("Filament IndirectLight and Skybox: image::ktx::createTexture of "
                 "environment_ibl.ktx (reflections, and its 'sh' key through "
                 "Ktx1Bundle::getSphericalHarmonics for IndirectLight::Builder::irradiance(3, "
                 "sh)) and of environment_skybox.ktx, as cmgen's files are loaded"),
}


_CUBE_WORDS = {
    "gltf": ("+X, -X, +Y, -Y, +Z, -Z in the OpenGL/Vulkan/KTX2 table: a raw texture(cube, "
             "world_dir) in glTF's world frame (glTF Sample Viewer, glTF-IBL-Sampler's files) "
             "returns world_dir's light"),
    "threejs": ("mirrored in x for three.js, which samples a CubeTexture at (-x, y, z) "
                "(flipEnvMap = -1): three.js reads world_dir's light"),
    "bevy": ("mirrored in z for Bevy, which samples environment maps at (x, y, -z) "
             "(environment_map.wesl): Bevy reads world_dir's light"),
}


def _format_code(target: str, vk_format: int | str | None) -> int:
    code = _DEFAULT_FORMAT[target] if vk_format is None else ktx2._check_format(vk_format)
    if code not in _ALLOWED_FORMATS[target]:
        names = ", ".join(ktx2._FORMATS[c][0] for c in _ALLOWED_FORMATS[target])
        raise ValueError(f"--vk-format {ktx2._FORMATS[code][0]} cannot hold a {target} export "
                         f"(SH coefficients are signed); use one of {names}")
    return code


def _finite(store_path: Any, name: str, a: np.ndarray) -> None:
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:
        raise StoreError(f"{store_path}: array {name!r} holds {bad} non-finite values (NaN or "
                         "inf); the store is damaged")


def export_grid(
    store_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    target: EngineTarget,
    vk_format: int | str | None = None,
    zstd: bool = False,
    probe: str | tuple[int, int, int] | None = None,
    cube_convention: CubeConvention = "gltf",
    sh: SHKind = "deringed",
) -> list[Path]:
    """Export a store for ``target`` into ``out_dir``; returns the files written (manifest last).

    The SH the three.js atlas and ``sh.json`` carry are the deringed ones by default (each
    probe's irradiance non-negative: three.js clamps negative irradiance to black), ``sh="raw"``
    the stored projection (:func:`probegrid.jobs.export.read_sh`); the manifest says which.

    Raises ``StoreError`` / ``ValueError`` (one line) for a damaged store, an unknown target or
    format, a probe outside the grid, or an ``out_dir`` that holds something else, before
    writing anything.
    """
    if target not in TARGETS:
        raise ValueError(f"--target must be one of {', '.join(TARGETS)}, got {target!r}")
    if target == "filament":
        return _export_filament(store_path, out_dir, vk_format=vk_format, zstd=zstd,
                                probe=probe, cube_convention=cube_convention, sh=sh)
    fmt = _format_code(target, vk_format)
    if probe is not None and target != "ktx2":
        raise ValueError("--probe applies to --target ktx2 (three.js and Bevy take the grid)")
    if cube_convention not in engines.CUBE_MIRROR:
        raise ValueError(f"--cube-convention must be one of {', '.join(engines.CUBE_MIRROR)}, "
                         f"got {cube_convention!r}")
    if cube_convention != "gltf" and target != "ktx2":
        raise ValueError("--cube-convention applies to --target ktx2 (cube maps)")
    if sh not in SH_MEANING:
        raise ValueError(f"--sh must be one of {', '.join(SH_MEANING)}, got {sh!r}")
    t0 = time.perf_counter()
    store = open_store(store_path)
    grid = store.grid
    nx, ny, nz = grid.counts
    maps = _map_arrays(store)  # checks sh, diffuse and the specular levels' shapes
    recorded = store.valid_mask()
    valid = np.ones(grid.n_probes, dtype=bool) if recorded is None else recorded
    output_format = f"probegrid.export.{target}"
    out = prepare_output_dir(out_dir, output_format, create=False)  # refuse early
    ijk = None
    if probe is not None:
        ijk = parse_probe(probe, store) if isinstance(probe, str) else tuple(probe)
        parse_probe(",".join(map(str, ijk)), store)

    def grid_array(name: str) -> np.ndarray:
        a = np.asarray(store[name], dtype=np.float32)
        _finite(store.path, name, a[valid])  # invalid probes are replaced anyway
        return a.reshape((nx, ny, nz) + a.shape[1:])

    vgrid = valid.reshape(nx, ny, nz)
    files: list[dict[str, Any]] = []
    payload: dict[Path, Any] = {}  # everything is encoded before anything is written
    conv = conventions()
    kv = {"probegrid:conventions": json.dumps(conv, separators=(",", ":"))}
    doc: dict[str, Any] = {}
    filled = 0
    if target == "threejs":
        coeffs = read_sh(store, sh, valid=valid)
        _finite(store.path, "sh", coeffs[valid])
        filled_sh, filled = engines.fill_invalid(coeffs.reshape(nx, ny, nz, 9, 3), vgrid)
        atlas = engines.threejs_atlas(filled_sh)
        place = engines.threejs_placement(grid)
        payload[out / "lightprobegrid.ktx2"] = ktx2.encode_ktx2_parts(
            [atlas], kind="3d", vk_format=fmt, supercompression="zstd" if zstd else "none",
            key_values={**kv, "probegrid:content": "three.js LightProbeGrid SH atlas"})
        header = {
            **place, "atlas_size": [nx, ny, 7 * (nz + 2)], "padding": engines.THREEJS_PADDING,
            "dtype": ktx2._FORMATS[fmt][0],
            "packing": ["c0.rgb c1.r", "c1.gb c2.rg", "c2.b c3.rgb", "c4.rgb c5.r",
                        "c5.gb c6.rg", "c6.b c7.rgb", "c8.rgb 0"],
            "layout": ("sub-volume t in atlas slices t*(nz+2)+1 .. t*(nz+2)+nz, one padding "
                       "slice copied from the edge at each end; x fastest, then y, then z"),
            "sh": ("radiance L_lm, world frame (glTF/three.js: right-handed, +Y up), basis "
                   "index l(l+1)+m without Condon-Shortley phase: three's shGetIrradianceAt "
                   "applies the cosine lobe (0.886227 c0 ...)"),
            "sh_kind": sh, "sh_meaning": SH_MEANING[sh],
            "conventions": {k: conv[k] for k in ("world_frame", "color_space",
                                                 "radiance_units", "sh_basis",
                                                 "sh_coefficients")},
        }
        payload[out / "lightprobegrid.json"] = header
        files += [{"path": "lightprobegrid.ktx2", "kind": "threejs-atlas",
                   "vk_format": ktx2._FORMATS[fmt][0], "size": header["atlas_size"]},
                  {"path": "lightprobegrid.json", "kind": "threejs-header"}]
        doc = {"threejs": header}
    elif target == "bevy":
        amb, filled = engines.fill_invalid(engines.ambient_cube(grid_array("diffuse")), vgrid)
        volume = engines.bevy_volume(amb)
        if fmt == ktx2.VK_FORMAT_E5B9G9R9_UFLOAT_PACK32 and (volume < 0).any():
            raise ValueError(f"{int((volume < 0).sum())} negative diffuse values cannot be "
                             "stored as E5B9G9R9; use --vk-format R16G16B16A16_SFLOAT")
        payload[out / "irradiance_volume.ktx2"] = ktx2.encode_ktx2_parts(
            [volume], kind="3d", vk_format=fmt, supercompression="zstd" if zstd else "none",
            key_values={**kv, "probegrid:content": "Bevy IrradianceVolume ambient cubes"})
        transform = engines.bevy_transform(grid)
        files.append({"path": "irradiance_volume.ktx2", "kind": "bevy-irradiance-volume",
                      "vk_format": ktx2._FORMATS[fmt][0], "size": [nx, 2 * ny, 3 * nz]})
        doc = {"bevy": {
            "transform": transform,
            "layout": ("(nx, 2 ny, 3 nz) texels; depth slabs x, y, z of nz slices each; rows "
                       "0..ny-1 the positive direction, ny..2ny-1 the negative one (as "
                       "irradiance_volume.wesl samples: +0.5 in v when N < 0)"),
            "content": "irradiance / pi toward +-X, +-Y, +-Z (the store's diffuse map along "
                       "the axes), world frame (right-handed, +Y up, as Bevy's)",
            "intensity": "IrradianceVolume.intensity scales it; 1 reproduces the store's units",
        }}
    else:
        names = [name for name, kind, _ in maps if kind == "specular"]
        select = (slice(None) if ijk is None else
                  int(store.probe_index(*ijk)))
        diffuse = np.asarray(store["diffuse"][select], dtype=np.float32)
        chain = [np.asarray(store[n][select], dtype=np.float32) for n in names]
        coeffs = (read_sh(store, sh, valid=valid) if ijk is None
                  else read_sh(store, sh, index=select))
        if ijk is None:
            filled_d, filled = engines.fill_invalid(
                diffuse.reshape((nx, ny, nz) + diffuse.shape[1:]), vgrid)
            diffuse = filled_d.reshape(diffuse.shape)
            chain = [engines.fill_invalid(c.reshape((nx, ny, nz) + c.shape[1:]), vgrid)[0]
                     .reshape(c.shape) for c in chain]
            coeffs = engines.fill_invalid(coeffs.reshape(nx, ny, nz, 9, 3),
                                          vgrid)[0].reshape(coeffs.shape).astype(np.float64)
        for name, a in [("diffuse", diffuse), ("sh", coeffs)] + list(zip(names, chain)):
            _finite(store.path, name, a)
        mirror = engines.CUBE_MIRROR[cube_convention]
        diffuse = engines.mirror_cube(diffuse, mirror)
        chain = [engines.mirror_cube(c, mirror) for c in chain]
        layered = ijk is None
        sc: Literal["none", "zstd"] = "zstd" if zstd else "none"
        payload[out / "diffuse.ktx2"] = ktx2.encode_ktx2_parts(
            [diffuse], kind="cube", vk_format=fmt, layered=layered, supercompression=sc,
            key_values={**kv, "probegrid:content": "diffuse: irradiance / pi"})
        files.append({"path": "diffuse.ktx2", "kind": "diffuse", "levels": 1,
                      "vk_format": ktx2._FORMATS[fmt][0], "layers": grid.n_probes if layered
                      else None})
        if chain:
            payload[out / "specular.ktx2"] = ktx2.encode_ktx2_parts(
                chain, kind="cube", vk_format=fmt, layered=layered, supercompression=sc,
                key_values={**kv, "probegrid:content": "GGX specular chain, level k at "
                            "perceptual roughness k / (levels - 1)"})
            n_lv = len(chain)
            files.append({"path": "specular.ktx2", "kind": "specular", "levels": n_lv,
                          "roughness": [k / (n_lv - 1) if n_lv > 1 else 0.0
                                        for k in range(n_lv)],
                          "vk_format": ktx2._FORMATS[fmt][0],
                          "layers": grid.n_probes if layered else None})
        payload[out / "sh.json"] = sh_document(
            coeffs, sh, conv, order="probe index (i ny + j) nz + k" if layered
            else f"probe {list(ijk)}")
        files.append({"path": "sh.json", "kind": "sh", "sh": sh})
        doc = {"ktx2": {"layers": ("one cube per probe, layer = store probe index "
                                   "(i ny + j) nz + k") if layered else f"probe {list(ijk)}",
                        "probe_valid": None if layered else bool(valid[select]),
                        "cube_convention": cube_convention,
                        "faces": _CUBE_WORDS[cube_convention]}}

    # --- write ------------------------------------------------------------------------------
    previous = listed_files(out)  # an earlier export's files (its manifest goes now)
    prepare_output_dir(out, output_format)
    remove_stale(out, previous, {p.name for p in payload} | {"manifest.json"})
    written: list[Path] = []
    for path, data in payload.items():
        if isinstance(data, list):  # a KTX2 file's parts
            ktx2.write_parts(path, data)
        elif path.name == "sh.json":  # thousands of numbers: compact
            text = json.dumps(data, separators=(",", ":"), allow_nan=False) + "\n"
            ktx2.write_parts(path, [text.encode()])
        else:
            atomic_write_json(path, data)
        written.append(path)
    manifest = {
        "format": output_format, "format_version": 1, "probegrid_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "store": str(Path(store_path)), "target": target, "consumer": _CONSUMERS[target],
        "grid": {"counts": [nx, ny, nz], "bounds_min": list(grid.bounds_min),
                 "bounds_max": list(grid.bounds_max),
                 "probe_position": "bounds_min + (i, j, k) * (max - min) / (counts - 1)"},
        "invalid_probes_filled": filled,
        **({"sh": {"kind": sh, "meaning": SH_MEANING[sh]}} if target != "bevy" else {}),
        "fill": "each invalid probe = mean of its valid (or already filled) face neighbours, "
                "filled outward from the valid probes",
        **doc, "conventions": conv, "files": files,
        "seconds": round(time.perf_counter() - t0, 4),
    }
    atomic_write_json(out / "manifest.json", manifest)
    written.append(out / "manifest.json")
    return written


def _export_filament(store_path: str | os.PathLike[str], out_dir: str | os.PathLike[str], *,
                     vk_format: int | str | None, zstd: bool,
                     probe: str | tuple[int, int, int] | None, cube_convention: str,
                     sh: SHKind) -> list[Path]:
    """:func:`export_grid` for ``target="filament"`` (module docstring): one probe's incoming
    cube filtered at Filament's roughness, written by
    :func:`probegrid.export.filament.write_filament_ibl`."""
    from probegrid.export import filament

    if vk_format is not None or zstd:
        raise ValueError("--vk-format and --zstd apply to KTX2 targets; --target filament "
                         "writes KTX1 R11F_G11F_B10F, as cmgen does")
    if cube_convention != "gltf":
        raise ValueError("--cube-convention applies to --target ktx2 (Filament reads the "
                         "OpenGL/KTX2 face table in glTF's frame)")
    if probe is None:
        raise ValueError("--target filament needs --probe I,J,K (Filament's IndirectLight is "
                         "one environment)")
    if sh not in SH_MEANING:
        raise ValueError(f"--sh must be one of {', '.join(SH_MEANING)}, got {sh!r}")
    t0 = time.perf_counter()
    store = open_store(store_path)
    ijk = parse_probe(probe, store) if isinstance(probe, str) else tuple(probe)
    parse_probe(",".join(map(str, ijk)), store)
    if "incoming" not in store.names:
        raise ValueError(f"{store_path}: the store has no incoming cubes, which --target "
                         "filament filters again at Filament's roughness; bake it with "
                         "--store-incoming")
    index = int(store.probe_index(*ijk))
    cube = np.asarray(store["incoming"][index], dtype=np.float32)
    size = int(cube.shape[1])
    try:
        filament.check_size(size)
    except ValueError:
        raise ValueError(f"{store_path}: --target filament needs a face size of at least "
                         f"{2 * filament.MIN_MIP} (a power of two: mips down to "
                         f"{filament.MIN_MIP}^2), the store's is {size}; bake with "
                         f"--face-size {2 * filament.MIN_MIP} or more") from None
    coeffs = read_sh(store, sh, index=index)
    for name, a in (("incoming", cube), ("sh", coeffs)):
        _finite(store.path, name, a)
    output_format = "probegrid.export.filament"
    out = prepare_output_dir(out_dir, output_format, create=False)  # refuse early
    recorded = store.valid_mask()
    valid = None if recorded is None else bool(recorded[index])
    chain = filament.specular_chain(cube)

    previous = listed_files(out)
    prepare_output_dir(out, output_format)
    remove_stale(out, previous, {filament.IBL_FILE, filament.SKYBOX_FILE, "manifest.json"})
    files = filament.write_filament_ibl(out, chain, coeffs)
    grid = store.grid
    manifest = {
        "format": output_format, "format_version": 1, "probegrid_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "store": str(Path(store_path)), "target": "filament",
        "consumer": _CONSUMERS["filament"],
        "grid": {"counts": list(grid.counts), "bounds_min": list(grid.bounds_min),
                 "bounds_max": list(grid.bounds_max),
                 "probe_position": "bounds_min + (i, j, k) * (max - min) / (counts - 1)"},
        "probe": list(ijk), "probe_valid": valid,
        "sh": {"kind": sh, "meaning": SH_MEANING[sh]},
        "filament": {"source": "the probe's stored incoming cube, filtered at Filament's "
                               "roughness (the store's chain is at r = k / (levels - 1))"},
        "conventions": conventions(), "files": files,
        "seconds": round(time.perf_counter() - t0, 4),
    }
    atomic_write_json(out / "manifest.json", manifest)
    return [out / filament.IBL_FILE, out / filament.SKYBOX_FILE, out / "manifest.json"]
