"""Engine exports (probegrid.export.engines, probegrid.jobs.engine_export, ``probegrid export
--target``), checked by re-implementing each engine's lookup from its shader source in numpy:

* three.js ``getLightProbeGridIrradiance`` (lightprobes_pars_fragment.glsl.js, r187): clamp to
  texel centres, atlas z mapping, hardware trilinear filtering, unpacking and the irradiance
  polynomial;
* Bevy ``irradiance_volume_light`` (irradiance_volume.wesl): unit-cube position, texel-centre
  clamp, slab and sign-half offsets, the N^2 blend;
* cube lookups: the OpenGL face-selection table, three.js' ``(-x, y, z)`` and Bevy's
  ``(x, y, -z)``.

The linear store's SH and maps are affine in the probe position, so an engine's trilinear lookup
anywhere inside the grid must equal the affine field at that point: this checks the placement
(centre, size, half-cell offsets) as well as the packing. A lopsided environment (red toward +X,
green toward +Z) checks that each engine reads those colours toward those world directions.
Every KTX2 file is also read by npm's ktx-parse (skipped without node).
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
from node_readers import ktx_parse_dump, node_package_dir
from probe_stores import GRID, linear_store, linear_values, write_store

from probegrid.cli import main
from probegrid.core import diffuse, sh
from probegrid.core.sh.dering import dering
from probegrid.core.cubemap import texel_directions
from probegrid.core.grid import GridSpec
from probegrid.export import engines, ktx2
from probegrid.jobs.engine_export import export_grid
from probegrid.store import open_store


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("eng") / "s.probes"
    linear_store(path).close()
    return path


# ------------------------------------------------------------------------ samplers (GL rules)
def sample3d(tex: np.ndarray, uvw: np.ndarray) -> np.ndarray:
    """Trilinear filtering of a (D, H, W, C) texture at normalised (u, v, w), clamp to edge."""
    out = 0.0
    dims = np.array([tex.shape[2], tex.shape[1], tex.shape[0]])
    x = np.asarray(uvw, np.float64) * dims - 0.5
    i0 = np.floor(x).astype(int)
    f = x - i0
    for corner in range(8):
        o = np.array([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])
        idx = np.clip(i0 + o, 0, dims - 1)
        w = np.prod(np.where(o, f, 1.0 - f))
        out = out + w * tex[idx[2], idx[1], idx[0]].astype(np.float64)
    return out


def cube_lookup_texel(d) -> tuple[int, int, int]:
    """The texel an OpenGL cube-map lookup reads (GL 4.6 table 8.19: major axis, sc, tc)."""
    x, y, z = d
    ax = np.abs(d)
    if ax[0] >= ax[1] and ax[0] >= ax[2]:
        face, sc, tc, ma = (0, -z, -y, ax[0]) if x > 0 else (1, z, -y, ax[0])
    elif ax[1] >= ax[2]:
        face, sc, tc, ma = (2, x, z, ax[1]) if y > 0 else (3, x, -z, ax[1])
    else:
        face, sc, tc, ma = (4, x, -y, ax[2]) if z > 0 else (5, -x, -y, ax[2])
    return face, 0.5 * (sc / ma + 1), 0.5 * (tc / ma + 1)


def cube_sample(faces: np.ndarray, d) -> np.ndarray:
    """Bilinear sample of one face (directions away from face edges), GL lookup."""
    face, s, t = cube_lookup_texel(np.asarray(d, np.float64))
    img = faces[face][None]  # (1, n, n, C) as a one-slice 3D texture
    return sample3d(img, np.array([s, t, 0.5]))


def three_irradiance(atlas, header, p, n) -> np.ndarray:
    """three.js getLightProbeGridIrradiance, line by line."""
    lo, hi = np.array(header["min"]), np.array(header["max"])
    res = np.array(header["resolution"], np.float64)
    spacing = (hi - lo) / res
    sample_pos = np.asarray(p) + np.asarray(n) * spacing * 0.5
    uvw = np.clip((sample_pos - lo) / (hi - lo), 0.5 / res, 1.0 - 0.5 / res)
    nz = res[2]
    padded = nz + 2.0
    depth = 7.0 * padded
    base = uvw[2] * nz + 1.0
    s = [sample3d(atlas, np.array([uvw[0], uvw[1], (base + t * padded) / depth]))
         for t in range(7)]
    c = [s[0][:3], np.r_[s[0][3], s[1][:2]], np.r_[s[1][2:], s[2][0]], s[2][1:],
         s[3][:3], np.r_[s[3][3], s[4][:2]], np.r_[s[4][2:], s[5][0]], s[5][1:], s[6][:3]]
    x, y, z = n
    r = c[0] * 0.886227
    r = r + c[1] * 2.0 * 0.511664 * y + c[2] * 2.0 * 0.511664 * z + c[3] * 2.0 * 0.511664 * x
    r = r + c[4] * 2.0 * 0.429043 * x * y + c[5] * 2.0 * 0.429043 * y * z
    r = r + c[6] * (0.743125 * z * z - 0.247708) + c[7] * 2.0 * 0.429043 * x * z
    r = r + c[8] * 0.429043 * (x * x - y * y)
    return np.maximum(r, 0.0)


def bevy_irradiance(volume, transform, p, n) -> np.ndarray:
    """Bevy irradiance_volume_light for one volume, line by line (light_from_world = the
    inverse of translation * scale)."""
    atlas_res = np.array([volume.shape[2], volume.shape[1], volume.shape[0]], np.float64)
    res = atlas_res / np.array([1.0, 2.0, 3.0])
    unit = (np.asarray(p) - np.array(transform["translation"])) / np.array(transform["scale"])
    stp = np.clip((unit + 0.5) * res, 0.5, res - 0.5)
    uvw = stp / atlas_res
    neg = np.where(np.asarray(n) < 0, 0.5, 0.0)
    rgb_x = sample3d(volume, uvw + [0.0, neg[0], 0.0])
    rgb_y = sample3d(volume, uvw + [0.0, neg[1], 1.0 / 3.0])
    rgb_z = sample3d(volume, uvw + [0.0, neg[2], 2.0 / 3.0])
    nn = np.asarray(n, np.float64) ** 2
    return rgb_x[:3] * nn[0] + rgb_y[:3] * nn[1] + rgb_z[:3] * nn[2]


SUFFIXES = ("px", "nx", "py", "ny", "pz", "nz")
AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


# ------------------------------------------------------------------------ fill
def test_fill_invalid_interior_probe_of_affine_field_is_exact():
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(4.0), np.arange(3.0), indexing="ij"), -1)
    values = (1.5 + g @ np.array([0.5, -2.0, 3.0]))[..., None] * np.ones(2)
    valid = np.ones((5, 4, 3), bool)
    valid[2, 1, 1] = False
    broken = values.copy()
    broken[2, 1, 1] = 1e9
    out, count = engines.fill_invalid(broken, valid)
    assert count == 1
    np.testing.assert_allclose(out, values, rtol=0, atol=1e-5)


def test_fill_invalid_grows_from_the_valid_probes():
    values = np.arange(4 * 3 * 2, dtype=np.float64).reshape(4, 3, 2)
    valid = np.zeros((4, 3, 2), bool)
    valid[0, 0, 0] = True
    out, count = engines.fill_invalid(values, valid)
    assert count == 23 and np.all(out == 0.0)  # every probe copies the one valid probe
    valid[3, 2, 1] = True  # two sources: each probe averages what reached it first
    out, _ = engines.fill_invalid(values, valid)
    assert out[0, 0, 0] == 0 and out[3, 2, 1] == 23 and np.all((out >= 0) & (out <= 23))
    assert out[1, 0, 0] == 0 and out[2, 2, 1] == 23  # nearest source wins at distance 1
    with pytest.raises(ValueError, match="every probe is invalid"):
        engines.fill_invalid(values, np.zeros((4, 3, 2), bool))


# ------------------------------------------------------------------------ three.js
def test_threejs_atlas_packing_and_decoding(store, tmp_path):
    export_grid(store, tmp_path / "t", target="threejs", vk_format=109, sh="raw")
    tex = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2")
    header = json.loads((tmp_path / "t" / "lightprobegrid.json").read_text())
    nx, ny, nz = GRID.counts
    atlas = tex.levels[0]
    assert atlas.shape == (7 * (nz + 2), ny, nx, 4) and tex.kind == "3d"
    assert header["atlas_size"] == [nx, ny, 7 * (nz + 2)]
    want = np.asarray(open_store(store)["sh"]).reshape(nx, ny, nz, 9, 3)
    np.testing.assert_array_equal(engines.threejs_unpack(atlas, nz), want)
    # three's own packing, texel by texel: sub-volume t holds floats 4t..4t+3 of c0.rgb..c8.rgb
    flat = np.concatenate([want.reshape(nx, ny, nz, 27), np.zeros((nx, ny, nz, 1))], -1)
    for t in range(7):
        sub = atlas[t * (nz + 2):(t + 1) * (nz + 2)]
        np.testing.assert_array_equal(sub[1:-1].transpose(2, 1, 0, 3), flat[..., 4 * t:4 * t + 4])
        np.testing.assert_array_equal(sub[0], sub[1])  # padding copies the edge slices
        np.testing.assert_array_equal(sub[-1], sub[-2])
    # three.js' getProbePosition puts probe (i, j, k) exactly on the store's probe
    pos, size, res = (np.array(header[k], float) for k in ("position", "size", "resolution"))
    ijk = np.stack(np.meshgrid(*(np.arange(n) for n in (nx, ny, nz)), indexing="ij"), -1)
    three_pos = pos - size / 2 + (ijk.reshape(-1, 3) + 0.5) * size / res
    np.testing.assert_allclose(three_pos, GRID.positions(), atol=1e-12)


def test_threejs_shader_lookup_between_probes_equals_the_affine_field(store, tmp_path):
    export_grid(store, tmp_path / "t", target="threejs", vk_format=109, sh="raw")
    atlas = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2").levels[0]
    header = json.loads((tmp_path / "t" / "lightprobegrid.json").read_text())
    spacing = np.asarray(GRID.spacing)
    rng = np.random.default_rng(3)
    for _ in range(12):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        # the shader samples half a cell along the normal: keep that point inside the probes
        sample = GRID.lo + rng.uniform(0.05, 0.95, 3) * (GRID.hi - GRID.lo)
        p = sample - n * spacing * 0.5
        L = linear_values("sh", (9, 3), sample[None])[0]
        want = np.maximum(sh.irradiance(L, n[None])[0], 0.0)
        np.testing.assert_allclose(three_irradiance(atlas, header, p, n), want, rtol=1e-5,
                                   atol=1e-5)


# ------------------------------------------------------------------------ Bevy
def test_bevy_volume_values_and_shader_lookup(store, tmp_path):
    export_grid(store, tmp_path / "b", target="bevy", vk_format=109)
    man = json.loads((tmp_path / "b" / "manifest.json").read_text())
    tex = ktx2.read_ktx2(tmp_path / "b" / "irradiance_volume.ktx2")
    nx, ny, nz = GRID.counts
    volume = tex.levels[0]
    assert volume.shape == (3 * nz, 2 * ny, nx, 4)
    tr = man["bevy"]["transform"]
    diff = np.asarray(open_store(store)["diffuse"])  # (P, 6, n, n, 3)
    amb = engines.ambient_cube(diff)  # (P, 6, 3)
    # at each probe, a normal along an axis reads the store's diffuse map toward that axis
    for idx, p in enumerate(GRID.positions()):
        for f, n in enumerate(AXES):
            np.testing.assert_allclose(bevy_irradiance(volume, tr, p, n), amb[idx, f],
                                       rtol=1e-6)
    # ... which is what a bilinear lookup of the diffuse cube along the axis returns
    for f, n in enumerate(AXES):
        np.testing.assert_allclose(cube_sample(diff[0], n), amb[0, f], rtol=1e-6)
    # between probes: the diffuse maps are affine in position, so is the ambient cube
    rng = np.random.default_rng(5)
    for _ in range(12):
        p = GRID.lo + rng.uniform(0.0, 1.0, 3) * (GRID.hi - GRID.lo)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        a = engines.ambient_cube(linear_values("diffuse", diff.shape[1:], p[None]))[0]
        want = sum(a[2 * k + (n[k] < 0)] * n[k] ** 2 for k in range(3))
        np.testing.assert_allclose(bevy_irradiance(volume, tr, p, n), want, rtol=1e-5)


# ------------------------------------------------------------------------ lopsided environment
def _lopsided_cube(n: int = 16) -> np.ndarray:
    d = texel_directions(n)
    red = 20.0 * np.maximum(d[..., 0], 0) ** 6
    green = 20.0 * np.maximum(d[..., 2], 0) ** 6
    return np.stack([red + 0.05, green + 0.05, np.full_like(red, 0.05)], -1).astype(np.float32)


@pytest.fixture(scope="module")
def lopsided(tmp_path_factory) -> Path:
    cube = _lopsided_cube()
    grid = GridSpec.from_counts((-1.0, 0.0, -1.0), (1.0, 1.0, 1.0), (2, 2, 2))
    P = grid.n_probes
    chain = [cube]
    while chain[-1].shape[1] > 1:  # a (blur-free) chain is enough to check orientation
        c = chain[-1]
        chain.append(c.reshape(6, c.shape[1] // 2, 2, c.shape[1] // 2, 2, 3).mean((2, 4)))
    arrays = {"sh": np.repeat(sh.project_cube(cube)[None].astype(np.float32), P, 0),
              "diffuse": np.repeat(diffuse.diffuse_exact(cube, 8)[None], P, 0),
              "valid": np.ones(P, bool)}
    for k, lv in enumerate(chain):
        arrays[f"specular_{k}"] = np.repeat(lv[None], P, 0)
    path = tmp_path_factory.mktemp("lop") / "lop.probes"
    write_store(path, grid, arrays).close()
    return path


def test_lopsided_environment_lands_where_each_engine_looks(lopsided, tmp_path):
    grid = open_store(lopsided).grid
    p = np.array([0.1, 0.5, -0.2])  # inside the grid; all probes hold the same light
    export_grid(lopsided, tmp_path / "t", target="threejs")
    atlas = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2").levels[0]
    header = json.loads((tmp_path / "t" / "lightprobegrid.json").read_text())
    three = np.array([three_irradiance(atlas, header, p, n) for n in AXES])
    export_grid(lopsided, tmp_path / "b", target="bevy")  # E5B9G9R9, as Bevy ships
    volume = ktx2.read_ktx2(tmp_path / "b" / "irradiance_volume.ktx2").levels[0]
    tr = json.loads((tmp_path / "b" / "manifest.json").read_text())["bevy"]["transform"]
    bevy = np.array([bevy_irradiance(volume, tr, p, n) for n in AXES])
    for name, e in (("three.js", three), ("bevy", bevy)):
        assert np.argmax(e[:, 0]) == 0, name  # red brightest toward world +X
        assert np.argmax(e[:, 1]) == 4, name  # green brightest toward world +Z
        assert e[0, 0] > 4 * e[1, 0] and e[4, 1] > 4 * e[5, 1], name
    # and the numbers: three.js' irradiance is pi times the diffuse map; Bevy's is the map
    diff = np.asarray(open_store(lopsided)["diffuse"][0])
    amb = engines.ambient_cube(diff)
    # E5B9G9R9: each component within half a 9-bit step of the texel's largest component
    assert np.all(np.abs(bevy - amb) <= amb.max(axis=-1, keepdims=True) * 2.0**-9 + 1e-7)
    np.testing.assert_allclose(three / np.pi, sh.irradiance(
        np.asarray(open_store(lopsided)["sh"][0], np.float64), AXES) / np.pi, rtol=2e-3,
        atol=2e-3)
    # cube maps: the texel each consumer's lookup reads for world +X is red, for +Z green
    lookups = {"gltf": lambda d: d, "threejs": lambda d: d * [-1, 1, 1],
               "bevy": lambda d: d * [1, 1, -1]}
    for conv, look in lookups.items():
        out = tmp_path / f"k-{conv}"
        export_grid(lopsided, out, target="ktx2", probe=(1, 0, 1), cube_convention=conv,
                    vk_format=109)
        spec = ktx2.read_ktx2(out / "specular.ktx2").levels[0]
        plus_x = cube_sample(spec, look(np.array([1.0, 0.0, 0.0])))
        plus_z = cube_sample(spec, look(np.array([0.0, 0.0, 1.0])))
        minus_x = cube_sample(spec, look(np.array([-1.0, 0.0, 0.0])))
        assert plus_x[0] > 10 and plus_x[1] < 0.1, conv
        assert plus_z[1] > 10 and plus_z[0] < 0.1, conv
        assert minus_x[0] < 0.1, conv
    assert grid.n_probes == 8


# ------------------------------------------------------------------------ files and CLI
@pytest.mark.slow
def test_cli_exports_every_target_and_ktx_parse_reads_them(store, tmp_path, tmp_path_factory,
                                                           capsys):
    for target in ("threejs", "bevy", "ktx2"):
        assert main(["export", str(store), "--target", target, "--sh", "raw", "--out",
                     str(tmp_path / target)]) == 0
        man = json.loads((tmp_path / target / "manifest.json").read_text())
        assert man["target"] == target and man["invalid_probes_filled"] == 0
        assert man["consumer"] and man["conventions"]["cube_face_order"][0] == "+X"
    assert main(["export", str(store), "--target", "ktx2", "--zstd", "--probe", "1,0,2",
                 "--out", str(tmp_path / "one")]) == 0
    files = sorted(tmp_path.glob("*/*.ktx2"))
    assert len(files) == 6
    base = node_package_dir(tmp_path_factory, "ktx-parse")
    for d in ktx_parse_dump(base, files):
        ours = ktx2.read_ktx2(d["file"])
        assert d["rewriteIdentical"], d["file"]
        assert (d["vkFormat"], d["pixelWidth"], d["pixelHeight"], d["pixelDepth"],
                d["layerCount"], d["faceCount"], d["levelCount"]) == (
            ours.vk_format, ours.pixel_width, ours.pixel_height, ours.pixel_depth,
            ours.layer_count, ours.face_count, ours.level_count)
        if d["supercompressionScheme"] == 0:
            for lv, (off, length, _) in zip(d["levels"], ours.level_index, strict=True):
                raw = base64.b64decode(lv["base64"])
                assert raw == Path(d["file"]).read_bytes()[off:off + length]
    # three's atlas as ktx-parse reads it, decoded here: the store's SH after half rounding
    d = next(x for x in ktx_parse_dump(base, [tmp_path / "threejs" / "lightprobegrid.ktx2"]))
    nx, ny, nz = GRID.counts
    atlas = np.frombuffer(base64.b64decode(d["levels"][0]["base64"]), "<f2").reshape(
        7 * (nz + 2), ny, nx, 4)
    want = np.asarray(open_store(store)["sh"]).reshape(nx, ny, nz, 9, 3)
    np.testing.assert_array_equal(engines.threejs_unpack(atlas.astype(np.float32), nz),
                                  want.astype(np.float16).astype(np.float32))
    # the per-probe export is probe (1, 0, 2)'s maps, layer-free
    one = ktx2.read_ktx2(tmp_path / "one" / "diffuse.ktx2")
    s = open_store(store)
    assert one.layer_count == 0 and one.supercompression_scheme == 2
    np.testing.assert_array_equal(one.levels[0][..., :3], np.asarray(
        s["diffuse"][int(s.probe_index(1, 0, 2))]).astype(np.float16).astype(np.float32))
    capsys.readouterr()


def test_invalid_probes_are_filled_and_counted(tmp_path):
    from probe_stores import linear_arrays

    arrays = linear_arrays()
    arrays["valid"][[4, 7]] = False
    arrays["sh"][[4, 7]] = np.nan  # whatever an invalid probe holds is replaced
    path = tmp_path / "v.probes"
    write_store(path, GRID, arrays).close()
    export_grid(path, tmp_path / "t", target="threejs", vk_format=109, sh="raw")
    man = json.loads((tmp_path / "t" / "manifest.json").read_text())
    assert man["invalid_probes_filled"] == 2
    atlas = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2").levels[0]
    got = engines.threejs_unpack(atlas, GRID.counts[2]).reshape(-1, 9, 3)
    assert np.all(np.isfinite(got))
    np.testing.assert_array_equal(np.delete(got, [4, 7], 0), np.delete(arrays["sh"], [4, 7], 0))


@pytest.mark.parametrize("args, message", [
    (["--target", "threejs", "--vk-format", "E5B9G9R9_UFLOAT_PACK32"], "signed"),
    (["--target", "bevy", "--probe", "0,0,0"], "--probe applies"),
    (["--target", "ktx2", "--probe", "9,0,0"], "outside the grid"),
    (["--target", "ktx2", "--vk-format", "R8"], "not supported"),
    (["--target", "bevy", "--cube-convention", "bevy"], "cube-convention"),
    ([], "needs --probe"),
    (["--probe", "0,0,0", "--zstd"], "apply to --target"),
    (["--target", "bevy", "--layout", "hcross"], "apply to image exports"),
])
def test_cli_bad_options_are_one_line_errors(store, tmp_path, capsys, args, message):
    out = tmp_path / "o"
    assert main(["export", str(store), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists()


# ------------------------------------------------------------------------ SH forms, filter ktx2
def test_sh_forms_evaluate_to_the_same_irradiance_in_each_consumer():
    from probegrid.export import shforms

    L = sh.project_cube(_lopsided_cube())
    rng = np.random.default_rng(9)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    x, y, z = n.T
    want = sh.irradiance(L, n)  # (50, 3)
    # Filament: Irradiance_SphericalHarmonics (light_indirect.fs), irradiance / pi
    f = shforms.filament_prescaled(L)
    poly = np.stack([np.ones_like(x), y, z, x, y * x, y * z, 3 * z * z - 1, z * x,
                     x * x - y * y], -1)
    np.testing.assert_allclose(poly @ f, want / np.pi, rtol=1e-12, atol=1e-12)
    # Babylon: SH3ylmBasisConstants x SH3ylmBasisTrigonometricTerms, irradiance coefficients
    const = np.array([np.sqrt(1 / (4 * np.pi)), -np.sqrt(3 / (4 * np.pi)),
                      np.sqrt(3 / (4 * np.pi)), -np.sqrt(3 / (4 * np.pi)),
                      np.sqrt(15 / (4 * np.pi)), -np.sqrt(15 / (4 * np.pi)),
                      np.sqrt(5 / (16 * np.pi)), -np.sqrt(15 / (4 * np.pi)),
                      np.sqrt(15 / (16 * np.pi))])
    e = shforms.ext_lights_image_based(L)
    np.testing.assert_allclose((poly * const) @ e, want, rtol=1e-12, atol=1e-12)
    # three.js: shGetIrradianceAt on the radiance coefficients as they are
    t = np.asarray(shforms.sh_forms(L)["threejs"]["coefficients"])
    three = (t[0] * 0.886227 + np.outer(y, t[1]) * 2 * 0.511664 + np.outer(z, t[2]) * 2 * 0.511664
             + np.outer(x, t[3]) * 2 * 0.511664 + np.outer(x * y, t[4]) * 2 * 0.429043
             + np.outer(y * z, t[5]) * 2 * 0.429043 + np.outer(0.743125 * z * z - 0.247708, t[6])
             + np.outer(x * z, t[7]) * 2 * 0.429043 + np.outer(x * x - y * y, t[8]) * 0.429043)
    np.testing.assert_allclose(three, want, rtol=1e-5, atol=2e-5)  # three: 6-digit constants


@pytest.mark.slow
def test_filter_format_ktx2_matches_the_exr_maps(tmp_path, tmp_path_factory):
    from probegrid import imageio
    from probegrid.filter import FilterSettings
    from probegrid.jobs.filter import run_filter

    cube = _lopsided_cube(16)
    faces = []
    for f, name in enumerate(SUFFIXES):
        faces.append(tmp_path / f"{name}.exr")
        imageio.write_image(faces[-1], cube[f], half=False)
    common = {"layout": "faces", "size": 16, "diffuse_size": 4, "lut_size": 4,
              "previews": False}
    run_filter(faces, tmp_path / "k", FilterSettings(format="ktx2", **common))
    run_filter(faces, tmp_path / "e", FilterSettings(format="exr", **common))
    spec = ktx2.read_ktx2(tmp_path / "k" / "specular.ktx2")
    diff = ktx2.read_ktx2(tmp_path / "k" / "diffuse.ktx2")
    assert spec.kind == "cube" and spec.level_count == 5 and spec.vk_format == 97
    assert diff.level_count == 1 and diff.pixel_width == 4
    for k, lv in enumerate(spec.levels):
        exr = np.stack([imageio.read_image(tmp_path / "e" / f"specular_m{k}_{s}.exr")
                        for s in SUFFIXES])
        np.testing.assert_array_equal(lv[..., :3], exr)
    # level 0 is the unblurred input; a raw GL lookup (Sample Viewer) reads red at +X
    np.testing.assert_array_equal(spec.levels[0][..., :3],
                                  cube.astype(np.float16).astype(np.float32))
    assert cube_sample(spec.levels[0], [1.0, 0, 0])[0] > 10
    assert cube_sample(spec.levels[0], [0, 0, 1.0])[1] > 10
    man = json.loads((tmp_path / "k" / "manifest.json").read_text())
    assert {f["path"] for f in man["files"]} >= {"specular.ktx2", "diffuse.ktx2", "sh.json"}
    shdoc = json.loads((tmp_path / "k" / "sh.json").read_text())
    assert set(shdoc["consumers"]) == {"threejs", "filament", "ext_lights_image_based"}
    # mirrored for three.js: its (-x, y, z) lookup of world +X reads the red texels
    run_filter(faces, tmp_path / "t", FilterSettings(format="ktx2", cube_convention="threejs",
                                                     **common))
    three = ktx2.read_ktx2(tmp_path / "t" / "specular.ktx2").levels[0]
    assert cube_sample(three, [-1.0, 0, 0])[0] > 10 and cube_sample(three, [1.0, 0, 0])[0] < 0.1
    assert cube_sample(three, [0, 0, 1.0])[1] > 10
    base = node_package_dir(tmp_path_factory, "ktx-parse")
    for d in ktx_parse_dump(base, [tmp_path / "k" / "specular.ktx2",
                                   tmp_path / "k" / "diffuse.ktx2"]):
        assert d["rewriteIdentical"] and d["faceCount"] == 6 and d["vkFormat"] == 97


def test_filter_format_ktx2_takes_vk_format_and_zstd_as_export_does(tmp_path, capsys):
    from probegrid import imageio

    sky = tmp_path / "sky.exr"
    imageio.write_image(sky, np.abs(np.sin(np.arange(16 * 32 * 3, dtype=np.float32))).reshape(
        16, 32, 3) + 0.1, half=False)
    small = ["--size", "8", "--diffuse-size", "4", "--lut-size", "4", "--no-previews"]
    assert main(["filter", str(sky), "--out", str(tmp_path / "f"), "--format", "ktx2",
                 "--float", *small]) == 0
    assert main(["filter", str(sky), "--out", str(tmp_path / "e"), "--format", "ktx2",
                 "--vk-format", "E5B9G9R9_UFLOAT_PACK32", "--zstd", *small]) == 0
    for name in ("specular.ktx2", "diffuse.ktx2"):
        full, packed = (ktx2.read_ktx2(tmp_path / d / name) for d in ("f", "e"))
        assert full.vk_format == 109 and full.supercompression_scheme == 0
        assert packed.vk_format == 123 and packed.supercompression_scheme == 2
        assert packed.level_count == full.level_count
        for a, b in zip(packed.levels, full.levels, strict=True):  # 9-bit shared exponent
            np.testing.assert_allclose(a[..., :3], b[..., :3], rtol=2 ** -8, atol=1e-6)
    man = json.loads((tmp_path / "e" / "manifest.json").read_text())
    assert {f["dtype"] for f in man["files"] if f["path"].endswith(".ktx2")} == {
        "E5B9G9R9_UFLOAT_PACK32"}
    assert man["settings"]["zstd"] is True
    for bad, words in [(["--vk-format", "R16G16B16A16_SFLOAT"], "apply to --format ktx2"),
                       (["--zstd"], "apply to --format ktx2"),
                       (["--format", "ktx2", "--float", "--vk-format",
                         "R16G16B16A16_SFLOAT"], "not both")]:
        assert main(["filter", str(sky), "--out", str(tmp_path / "x"), *bad, *small]) == 2
        assert words in capsys.readouterr().err
    capsys.readouterr()


def test_service_maps_answer_format_ktx2(store):
    """``/maps?format=ktx2``: a one-level float32 cube equal to the npy answer; layout=cross is
    the cross as a 2D texture (the service's fast path and FastAPI agree on both)."""
    import asyncio
    import io

    import httpx

    from service.main import create_app
    from service.settings import Settings

    app = create_app([store], Settings())
    q = "/v1/grids/s/maps/specular?x=0.75&y=0.25&z=1.5&level=1"

    async def fetch() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.get(q + "&format=ktx2"), await c.get(q + "&format=npy"),
                    await c.get(q + "&format=ktx2&layout=cross")]

    ktx, npy, cross = asyncio.run(fetch())
    assert ktx.status_code == 200 and ktx.headers["content-type"] == "image/ktx2"
    tex = ktx2.read_ktx2(ktx.content)
    assert tex.kind == "cube" and tex.level_count == 1 and tex.vk_format == 109
    np.testing.assert_array_equal(tex.levels[0][..., :3],
                                  np.load(io.BytesIO(npy.content), allow_pickle=False))
    assert json.loads(tex.key_values["probegrid:meta"].rstrip(b"\0"))["level"] == 1
    assert cross.status_code == 200 and ktx2.read_ktx2(cross.content).kind == "2d"


# ------------------------------------------------------------ many probes: --probe all / a box
@pytest.mark.slow
def test_export_probe_all_and_box_write_every_probe_and_name_the_invalid(tmp_path, capsys):
    from probe_stores import linear_arrays

    from probegrid import imageio

    arrays = linear_arrays(GRID)
    grid_ijk = [(i, j, k) for i in range(3) for j in range(2) for k in range(3)]
    invalid = [(0, 1, 2), (2, 0, 1)]
    for ijk in invalid:
        arrays["valid"][GRID.probe_index(*ijk)] = False
    path = tmp_path / "v.probes"
    write_store(path, GRID, arrays).close()
    out = tmp_path / "all"
    capsys.readouterr()
    assert main(["export", str(path), "--probe", "all", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "wrote 18 probes" in said and "2 of them invalid" in said
    assert "0,1,2" in said and "2,0,1" in said
    man = json.loads((out / "manifest.json").read_text())
    assert man["format"] == "probegrid.probes-export" and man["count"] == 18
    assert [tuple(p["ijk"]) for p in man["probes"]] == grid_ijk
    assert sorted(map(tuple, man["invalid"])) == sorted(invalid)
    files = 0
    for p in man["probes"]:
        ijk, index = tuple(p["ijk"]), GRID.probe_index(*p["ijk"])
        assert p["index"] == index and p["valid"] == (ijk not in invalid)
        np.testing.assert_allclose(p["position"], arrays["positions"][index])
        sub = out / "_".join(map(str, ijk))
        files += len(list(sub.iterdir()))
        got = np.stack([imageio.read_image(sub / f"diffuse_{s}.exr") for s in
                        ("px", "nx", "py", "ny", "pz", "nz")])
        np.testing.assert_array_equal(got, arrays["diffuse"][index])
        spec = np.stack([imageio.read_image(sub / f"specular_m2_{s}.exr") for s in
                         ("px", "nx", "py", "ny", "pz", "nz")])
        np.testing.assert_array_equal(spec, arrays["specular_2"][index])
        sh_doc = json.loads((sub / "sh.json").read_text())  # deringed by default
        np.testing.assert_array_equal(sh_doc["coefficients"], dering(
            arrays["sh"][index:index + 1].astype(np.float64))[0][0])
        assert sh_doc["sh"] == "deringed"
        prev = imageio.read_image(sub / "preview_diffuse.png")
        assert prev.shape[:2] == (12, 16)  # hcross of 4^2 faces
        assert (sub / "preview_specular.png").is_file()
        assert (sub / "preview_incoming.png").is_file()
    assert f"({files + 1} files)" in said
    # a box, corners included, in store order
    box = tmp_path / "box"
    assert main(["export", str(path), "--probe", "1,0,1:2,1,2", "--out", str(box),
                 "--no-previews"]) == 0
    man = json.loads((box / "manifest.json").read_text())
    assert [tuple(p["ijk"]) for p in man["probes"]] == [
        (1, 0, 1), (1, 0, 2), (1, 1, 1), (1, 1, 2), (2, 0, 1), (2, 0, 2), (2, 1, 1), (2, 1, 2)]
    assert not list(box.glob("*/preview_*.png"))
    assert [tuple(p) for p in man["invalid"]] == [(2, 0, 1)]  # the one inside the box


def test_export_probe_box_refusals_write_nothing(tmp_path, capsys):
    from probe_stores import linear_arrays

    arrays = linear_arrays(GRID)
    arrays["specular_1"][GRID.probe_index(2, 1, 2), 3, 1, 1, 0] = np.nan
    path = tmp_path / "n.probes"
    write_store(path, GRID, arrays).close()
    for sel, words in (("2,0,0:1,1,1", "must not exceed"), ("0,0,0:3,0,0", "outside the grid"),
                       ("0,0:1,1,1", "three integers"), ("al", "three integers"),
                       ("all", "probe (2, 1, 2)"), ("1,1,1:2,1,2", "1 in 'specular_1'")):
        out = tmp_path / "o"
        capsys.readouterr()
        assert main(["export", str(path), "--probe", sel, "--out", str(out)]) != 0
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, (sel, err)
        assert not out.exists()


# ------------------------------------------------------------------------ which SH is exported
def _ringing_store(path: Path, *, stored_deringed: bool) -> dict[str, np.ndarray]:
    """The linear store with probe 5's SH replaced by the projection of a light from +X (its
    irradiance rings negative at 120 degrees from +X); with ``stored_deringed``, a bake's
    ``sh_deringed`` extra beside it (scaled by 0.5, so that a test sees which array an export
    read)."""
    from probe_stores import linear_arrays

    from probegrid.core.conventions import conventions
    from probegrid.store import ArraySpec, StoreWriter

    arrays = linear_arrays(GRID)
    arrays["sh"][5] = sh.project_samples(np.full((1, 3), 40.0), [[1.0, 0.0, 0.0]], [1.0])
    specs = {name: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str, description=name)
             for name, a in arrays.items()}
    writer = StoreWriter.create(path, arrays=specs, grid=GRID, conventions=conventions(),
                                scene_hash="ringing", bake={"synthetic": True})
    writer.write(np.arange(GRID.n_probes), arrays)
    if stored_deringed:
        writer.add_extra("sh_deringed", (0.5 * dering(arrays["sh"].astype(np.float64))[0])
                         .astype(np.float32))
    writer.finish(quality={"invalid_probes": 0}).close()
    return arrays


def test_exports_carry_the_deringed_sh_by_default_and_raw_on_request(tmp_path, capsys):
    path = tmp_path / "r.probes"
    arrays = _ringing_store(path, stored_deringed=False)
    raw = arrays["sh"].astype(np.float64)
    # (a band-2 delta's irradiance: 40 (1/4 + t/2 + 5/32 (3t^2 - 1)), -1.5625 at t = -1/2)
    minus_x = np.array([[-0.5, np.sqrt(0.75), 0.0]])
    assert sh.irradiance(raw[5], minus_x)[0].max() < -1.5  # the raw projection rings
    want = dering(raw)[0]
    nz = GRID.counts[2]
    # three.js: the atlas holds the deringed SH (three would clamp the ring to black)
    assert main(["export", str(path), "--target", "threejs", "--vk-format",
                 "R32G32B32A32_SFLOAT", "--out", str(tmp_path / "t")]) == 0
    atlas = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2").levels[0]
    got = engines.threejs_unpack(atlas, nz).reshape(-1, 9, 3)
    np.testing.assert_array_equal(got, want.astype(np.float32))
    assert sh.irradiance(got[5].astype(np.float64), minus_x)[0].min() >= 0.0
    man = json.loads((tmp_path / "t" / "manifest.json").read_text())
    header = json.loads((tmp_path / "t" / "lightprobegrid.json").read_text())
    assert man["sh"]["kind"] == "deringed" and header["sh_kind"] == "deringed"
    # raw on request, and the manifest says so
    assert main(["export", str(path), "--target", "threejs", "--sh", "raw", "--vk-format",
                 "R32G32B32A32_SFLOAT", "--out", str(tmp_path / "traw")]) == 0
    atlas = ktx2.read_ktx2(tmp_path / "traw" / "lightprobegrid.ktx2").levels[0]
    np.testing.assert_array_equal(engines.threejs_unpack(atlas, nz).reshape(-1, 9, 3),
                                  arrays["sh"])
    assert json.loads((tmp_path / "traw" / "manifest.json").read_text())["sh"]["kind"] == "raw"
    # the ktx2 target's and the per-probe export's sh.json: deringed, with consumer forms
    assert main(["export", str(path), "--target", "ktx2", "--out", str(tmp_path / "k")]) == 0
    doc = json.loads((tmp_path / "k" / "sh.json").read_text())
    np.testing.assert_array_equal(doc["coefficients"], want.astype(np.float32))
    assert doc["sh"] == "deringed"
    assert json.loads((tmp_path / "k" / "manifest.json").read_text())["sh"]["kind"] == "deringed"
    i, j, k = (int(x) for x in np.unravel_index(5, GRID.counts))
    assert main(["export", str(path), "--probe", f"{i},{j},{k}", "--out",
                 str(tmp_path / "p")]) == 0
    doc = json.loads((tmp_path / "p" / "sh.json").read_text())
    np.testing.assert_array_equal(doc["coefficients"], want[5])
    # export's sh.json carries the consumers' forms too, as filter's does
    from probegrid.export.shforms import sh_forms

    assert doc["consumers"] == json.loads(json.dumps(sh_forms(want[5])))
    assert json.loads((tmp_path / "p" / "manifest.json").read_text())["sh"]["kind"] == "deringed"
    capsys.readouterr()


def test_exports_read_the_stores_deringed_sh_when_it_has_them(tmp_path):
    path = tmp_path / "d.probes"
    arrays = _ringing_store(path, stored_deringed=True)
    export_grid(path, tmp_path / "t", target="threejs", vk_format=109)
    atlas = ktx2.read_ktx2(tmp_path / "t" / "lightprobegrid.ktx2").levels[0]
    stored = np.asarray(open_store(path)["sh_deringed"])
    np.testing.assert_array_equal(
        engines.threejs_unpack(atlas, GRID.counts[2]).reshape(-1, 9, 3), stored)
    assert not np.array_equal(stored, arrays["sh"])
