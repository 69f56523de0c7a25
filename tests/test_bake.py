"""Baking probe grids: furnace, inverse-square law, shadows, invalid probes, determinism across
executors, and a killed bake that resumes (probegrid.bake.driver, probegrid.bake.stages)."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake.driver import BakeSettings, bake
from probegrid.bake.environment import Environment
from probegrid.bake.executors import InlineExecutor, LocalExecutor
from probegrid.core.grid import GridSpec
from probegrid.core.lights import PointLight
from probegrid.core.sh import K0
from probegrid.scene import Material, SceneBuilder, box_scene
from probegrid.store import StoreError, open_store

FAST = {"face_size": 8, "diffuse_size": 4, "moments_size": 4, "batch_size": 4}


def _arrays(store):
    """Every array of a store, its extras (the SH field, ...) included."""
    return {name: np.asarray(store.arrays[name])
            for name in [*store.names, *store.manifest.extras]}


@pytest.mark.parametrize("bounces", [0, 1, 2, 3])
def test_furnace_box_reaches_geometric_series(tmp_path, bounces):
    rho, le = 0.6, 2.0
    scene = box_scene((-1, -1, -1), (1, 1, 1), albedo=rho, emission=le, inward=True)
    grid = GridSpec.from_counts((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), (2, 2, 2))
    st = BakeSettings(bounces=bounces, **FAST)
    report = bake(scene, grid, tmp_path / "f.probes", settings=st)
    expected = le * (1 - rho ** (bounces + 1)) / (1 - rho)
    s = report.store
    np.testing.assert_allclose(s["diffuse"], expected, rtol=1e-3)  # 8^2 cosine quadrature
    for k in range(st.levels()):
        np.testing.assert_allclose(s[f"specular_{k}"], expected, rtol=2e-5)
    np.testing.assert_allclose(s["sh"][:, 0], 2 * np.sqrt(np.pi) * expected, rtol=2e-5)
    np.testing.assert_allclose(s["sh"][:, 1:], 0, atol=2e-5 * expected)
    assert report.quality["invalid_probes"] == 0
    assert report.quality["energy_max_error"] < 1e-3
    assert s.manifest.quality["sh_min_irradiance_over_pi"] == pytest.approx(expected, rel=1e-4)


def _lone_light_scene(intensity=10.0, wall=False, light_pos=(0.0, 0.0, 0.0)):
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    # something to trace: a small quad far behind the light (a scene needs triangles)
    b.add_quad((50, -0.1, -0.1), (0, 0, 0.2), (0, 0.2, 0), material=m)  # faces -X
    if wall:  # a 4 x 4 wall in the plane x = 1, facing -X (toward the light)
        b.add_quad((1, -2, -2), (0, 0, 4), (0, 4, 0), material=m)
    b.add_light(PointLight(light_pos, (1.0, 1.0, 1.0), intensity))
    return b.build()


def test_point_light_inverse_square(tmp_path):
    intensity = 10.0
    scene = _lone_light_scene(intensity)
    grid = GridSpec.from_counts((2, 0, 0), (4, 0, 0), (2, 1, 1))  # probes at d = 2 and 4
    s = bake(scene, grid, tmp_path / "p.probes",
             settings=BakeSettings(bounces=0, **{**FAST, "face_size": 16})).store
    d = np.array([2.0, 4.0])
    e = intensity / d**2
    # the cube's integral is the irradiance: L00 = Y00 * E
    np.testing.assert_allclose(s["sh"][:, 0, :], np.repeat((K0 * e)[:, None], 3, 1), rtol=1e-5)
    # diffuse texel looking back at the light (-X): irradiance / pi, clamped cosine ~ 1
    from probegrid.core.cubemap import direction_to_texel, texel_directions

    f, r, c = (int(a) for a in direction_to_texel(np.array([-1.0, 0.0, 0.0]), 4))
    cosine = -texel_directions(4)[f, r, c, 0]
    diffuse_toward = np.asarray(s["diffuse"])[:, f, r, c, 0]
    np.testing.assert_allclose(diffuse_toward * np.pi, e * cosine, rtol=0.01)
    assert diffuse_toward[0] / diffuse_toward[1] == pytest.approx(4.0, rel=1e-4)


def test_wall_casts_shadow(tmp_path):
    grid = GridSpec.from_counts((3, 0, 0), (3, 0, 0), (1, 1, 1))
    lit = bake(_lone_light_scene(), grid, tmp_path / "a.probes",
               settings=BakeSettings(bounces=0, **FAST)).store
    shadowed = bake(_lone_light_scene(wall=True), grid, tmp_path / "b.probes",
                    settings=BakeSettings(bounces=0, **FAST)).store
    assert lit["sh"][0, 0, 0] == pytest.approx(K0 * 10 / 9, rel=1e-5)
    assert shadowed["sh"][0, 0, 0] == 0.0


def test_direct_light_is_counted_once_at_every_bounce(tmp_path):
    """A point light over an endless floor, nothing else: the floor is lit by the light alone,
    so the radiance a probe sees on it is rho / pi I cos / d^2 after any number of bounces (the
    bounce grids must not carry the light's direct term into the surfaces a second time)."""
    from probegrid.bake.pattern import sample_pattern

    rho, intensity, light = 0.5, 20.0, np.array([0.0, 3.0, 0.0])
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(rho))
    b.add_quad((-500, 0, 500), (1000, 0, 0), (0, 0, -1000), material=m)  # faces +Y
    b.add_light(PointLight(tuple(light), (1.0, 1.0, 1.0), intensity))
    scene = b.build()
    grid = GridSpec.from_counts((-2, 0.5, -2), (2, 2.5, 2), (3, 3, 3))
    probe = 13  # the centre probe, (0, 1.5, 0)
    for bounces in (0, 1, 2):
        st = BakeSettings(bounces=bounces, store_incoming=True,
                          **{**FAST, "face_size": 16})
        s = bake(scene, grid, tmp_path / f"f{bounces}.probes", settings=st).store
        p = np.asarray(s["positions"][probe])
        d = sample_pattern(st)[0][3, :, :, 0]  # the -Y face's rays: all see the floor
        hit = p + (-p[1] / d[..., 1])[..., None] * d
        to_light = light - hit
        dist = np.linalg.norm(to_light, axis=-1)
        expected = rho / np.pi * intensity * (to_light[..., 1] / dist) / dist**2
        np.testing.assert_allclose(np.asarray(s["incoming"][probe])[3, ..., 0], expected,
                                   rtol=1e-4, err_msg=f"{bounces} bounces")


def test_a_sun_smaller_than_a_texel_keeps_its_energy(tmp_path):
    """Misses read the environment box-filtered to the texel's footprint: a bright 1-texel sun in
    a 128^2 sky reaches an 8^2 probe cube with its energy (a point lookup would catch it whole or
    miss it): the probe's texels are the sky's means over their solid angles."""
    from probegrid.core.cubemap import texel_solid_angles
    from probegrid.core.sampling import resample

    sky = np.full((6, 128, 128, 3), 0.2, np.float32)
    sky[2, 37, 90] = 5000.0  # on +Y, between the probe texels' centres
    scene = _lone_light_scene(intensity=0.0)
    grid = GridSpec.from_counts((0, 0, 0), (0, 0, 0), (1, 1, 1))
    st = BakeSettings(bounces=0, store_incoming=True, **FAST)
    s = bake(scene, grid, tmp_path / "sun.probes", settings=st,
             environment=Environment(faces=sky)).store

    def energy(cube):
        return np.einsum("fijc,fij->c", np.asarray(cube, np.float64),
                         texel_solid_angles(cube.shape[1]))

    incoming = np.asarray(s["incoming"][0])
    np.testing.assert_allclose(energy(incoming), energy(sky), rtol=1e-4)
    np.testing.assert_allclose(incoming, resample(sky, FAST["face_size"]), rtol=1e-5)
    assert s.manifest.bake["render"]["environment_lookup_size"] == FAST["face_size"]


def test_direct_light_can_be_left_out(tmp_path):
    grid = GridSpec.from_counts((3, 0, 0), (3, 0, 0), (1, 1, 1))
    s = bake(_lone_light_scene(), grid, tmp_path / "n.probes",
             settings=BakeSettings(bounces=0, direct=False, **FAST)).store
    assert float(np.abs(s["sh"][0]).max()) == 0.0


def test_probe_inside_solid_box_is_invalid(tmp_path):
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((-1, -1, -1), (1, 1, 1), material=m, inward=False)  # a solid box
    scene = b.build()
    grid = GridSpec.from_counts((0, 0, 0), (3, 0, 0), (2, 1, 1))  # one inside, one outside
    st = BakeSettings(bounces=0, relocate=False, **FAST)
    s = bake(scene, grid, tmp_path / "s.probes", settings=st,
             environment=Environment(color=(1, 1, 1))).store
    assert s["valid"].tolist() == [False, True]
    assert s["backface_fraction"][0] == pytest.approx(1.0)
    assert s.manifest.quality["invalid_probes"] == 1
    # relocation moves a probe just inside a wall out of it
    grid2 = GridSpec.from_counts((0.95, 0, 0), (5.95, 0, 0), (2, 1, 1))  # cell 5: may move 2.25
    s2 = bake(scene, grid2, tmp_path / "r.probes",
              settings=BakeSettings(bounces=0, **FAST),
              environment=Environment(color=(1, 1, 1))).store
    assert bool(s2["valid"][0]) and s2["positions"][0][0] > 1.0
    assert s2.manifest.quality["relocated_probes"] == 1


def test_probe_inside_a_double_sided_solid_is_invalid(tmp_path):
    """A double-sided box shows no backface from inside; the probe in it is still found (all
    its rays hit within half a cell) and, with relocation, moved out of it. A probe in a closed
    room larger than that stays valid."""
    b = SceneBuilder()
    room = b.add_material(Material.diffuse(0.5))
    solid = b.add_material(dataclasses.replace(Material.diffuse(0.5), double_sided=True))
    b.add_box((-3, -3, -3), (3, 3, 3), material=room, inward=True)  # a closed room
    b.add_box((-0.3, -0.3, -0.3), (0.3, 0.3, 0.3), material=solid)  # a small solid
    scene = b.build()
    grid = GridSpec.from_counts((0, 0, 0), (2, 0, 0), (2, 1, 1))  # cell 2: reach 1
    st = BakeSettings(bounces=0, relocate=False, **FAST)
    s = bake(scene, grid, tmp_path / "s.probes", settings=st).store
    assert s["valid"].tolist() == [False, True]
    assert s["backface_fraction"][0] == 0.0  # the backface test alone would keep it
    moved = bake(scene, grid, tmp_path / "m.probes",
                 settings=BakeSettings(bounces=0, **FAST)).store
    assert bool(moved["valid"][0]) and np.abs(moved["positions"][0]).max() > 0.3
    off = bake(scene, grid, tmp_path / "o.probes",
               settings=BakeSettings(bounces=0, relocate=False, enclosure=0, **FAST)).store
    # without the enclosure test the authored winding still finds it (probegrid.bake.inside)
    assert off["valid"].tolist() == [False, True]


def _room_scene():
    scene = box_scene((-2, 0, -2), (2, 3, 2), albedo=0.5, emission=0.0, inward=True,
                      lights=(PointLight((0.3, 2.0, 0.2), (1.0, 0.9, 0.8), 20.0),))
    return scene


def test_bake_is_bit_identical_across_executors_and_batches(tmp_path):
    scene = _room_scene()
    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 2, 2))
    st = BakeSettings(bounces=1, samples=2, seed=7, **FAST)
    a = _arrays(bake(scene, grid, tmp_path / "inline.probes", settings=st,
                     executor=InlineExecutor()).store)
    st2 = st.model_copy(update={"batch_size": 3})
    with LocalExecutor(2) as ex:
        b = _arrays(bake(scene, grid, tmp_path / "local.probes", settings=st2, executor=ex).store)
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert a["sh"][:, 0].min() > 0  # lit


def test_stored_maps_are_the_filters_of_the_stored_incoming_cube(tmp_path):
    """Diffuse and specular maps are the exact sums of the probe's own incoming cube (the
    matrix path, :mod:`probegrid.core.probefilter`), and the manifest says so."""
    from probegrid.core.diffuse import diffuse_exact
    from probegrid.core.specular import ggx_prefilter

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 1, 2))
    st = BakeSettings(bounces=1, store_incoming=True, **FAST)
    s = bake(_room_scene(), grid, tmp_path / "r.probes", settings=st).store
    assert "cached float32 matrix" in s.manifest.bake["filters"]["specular"]
    for i in range(grid.n_probes):
        cube = np.asarray(s["incoming"][i])
        np.testing.assert_allclose(s["diffuse"][i], diffuse_exact(cube, st.diffuse_size),
                                   rtol=1e-5)
        ref = ggx_prefilter(cube, levels=st.levels(), method="exact")
        for k in range(st.levels()):
            np.testing.assert_allclose(s[f"specular_{k}"][i], ref[k], rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_dask_local_cluster_bake_equals_local_bake(tmp_path):
    distributed = pytest.importorskip("distributed")
    from probegrid.bake.executors import DaskExecutor

    scene = _room_scene()
    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 2, 2))
    st = BakeSettings(bounces=1, samples=2, seed=3, **FAST)
    local = _arrays(bake(scene, grid, tmp_path / "l.probes", settings=st).store)
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=":0")
    with cluster, DaskExecutor(cluster.scheduler_address) as ex:
        dask = _arrays(bake(scene, grid, tmp_path / "d.probes", settings=st, executor=ex).store)
    for k in local:
        assert np.array_equal(local[k], dask[k]), k


def _start_cli_bake(out: Path, *, probes_done: int, stderr: int
                    ) -> tuple[list[str], subprocess.Popen]:
    """Start a slow CLI bake of the sample room into ``out`` (its own process group) and
    return its command and process once ``probes_done`` probes of the final stage are stored."""
    from probegrid.store import partial_progress

    glb = Path(__file__).resolve().parents[1] / "data" / "sample_room.glb"
    cmd = [sys.executable, "-m", "probegrid.cli", "bake", str(glb), "--out", str(out),
           "--grid", "4x3x4", "--face-size", "8", "--diffuse-size", "4", "--bounces", "0",
           "--workers", "1", "--batch-size", "2", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr, text=True,
                            start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline:
        prog = partial_progress(out) if out.with_name(out.name + ".partial").exists() else None
        if prog and prog[0] >= probes_done:
            return cmd, proc
        if proc.poll() is not None:
            pytest.fail("the bake finished before it could be stopped")
        time.sleep(0.05)
    pytest.fail("the bake made no progress")


@pytest.mark.slow
def test_killed_bake_leaves_nothing_loadable_and_resumes(tmp_path):
    out = tmp_path / "room.probes"
    cmd, proc = _start_cli_bake(out, probes_done=4, stderr=subprocess.DEVNULL)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    with pytest.raises(StoreError):
        open_store(out)
    with pytest.raises(StoreError):
        open_store(out.with_name(out.name + ".partial"))
    from probegrid.jobs.export import describe_store

    with pytest.raises(StoreError, match="unfinished bake"):
        describe_store(out)
    done = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "resumed" in done.stdout
    fresh = tmp_path / "fresh.probes"
    cmd2 = [*cmd]
    cmd2[cmd2.index(str(out))] = str(fresh)
    assert subprocess.run(cmd2, check=False, capture_output=True, timeout=300).returncode == 0
    a, b = _arrays(open_store(out)), _arrays(open_store(fresh))
    for k in a:
        assert np.array_equal(a[k], b[k]), k


@pytest.mark.slow
def test_sigterm_stops_a_bake_cleanly(tmp_path):
    """``kill PID`` stops a CLI bake like Ctrl-C: exit code 130, one line, its worker
    processes and temporary context file gone, nothing loadable left."""
    import tempfile

    from probegrid.cli import EXIT_INTERRUPTED

    out = tmp_path / "room.probes"
    _, proc = _start_cli_bake(out, probes_done=2, stderr=subprocess.PIPE)
    proc.send_signal(signal.SIGTERM)  # the CLI process only, as ``kill PID`` does
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert err.strip().splitlines()[-1] == "probegrid: interrupted"
    assert not list(Path(tempfile.gettempdir()).glob(f"probegrid-context-{proc.pid}-*"))
    with pytest.raises(ProcessLookupError):  # the process group (its workers) is gone
        for _ in range(100):
            os.killpg(proc.pid, 0)
            time.sleep(0.05)
    with pytest.raises(StoreError):
        open_store(out)


def test_resume_after_a_kill_inside_finish_keeps_the_quality_figures(tmp_path):
    """A bake killed after its manifest was written (inside ``finish``) resumes with every
    probe done: the quality figures are recomputed from the stored arrays (the energy ratio
    from the stored diffuse maps and SH), not lost."""
    import shutil

    from probegrid.store import partial_path

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 1, 2))
    st = BakeSettings(bounces=1, **FAST)
    first = bake(_room_scene(), grid, tmp_path / "a.probes", settings=st)
    shutil.copytree(tmp_path / "a.probes", partial_path(tmp_path / "b.probes"))
    again = bake(_room_scene(), grid, tmp_path / "b.probes", settings=st)
    assert again.resumed_probes == grid.n_probes
    for key in ("energy_max_error", "seam_score_mean", "sh_min_irradiance_over_pi"):
        assert again.quality[key] == pytest.approx(first.quality[key], rel=1e-4, abs=1e-7), key
    assert "energy" in again.summary()


def test_sh_min_is_the_minimum_irradiance_of_the_stored_sh(tmp_path):
    """The store's sh_min (the quality figure sh_min_irradiance_over_pi) is each probe's
    minimum of SH irradiance / pi over the sphere: a lower bound of a dense scan (16 384
    directions) of the stored coefficients, tight to the scan's resolution, per channel."""
    from probegrid.core import sh

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 2, 2))
    s = bake(_room_scene(), grid, tmp_path / "m.probes",
             settings=BakeSettings(bounces=1, **FAST)).store
    coeffs = np.asarray(s["sh"], np.float64)  # (P, 9, 3)
    k = np.arange(16384) + 0.5
    y = 1 - 2 * k / 16384
    phi = k * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - y * y)
    dirs = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)
    irr = sh.irradiance_coefficients(np.moveaxis(coeffs, 1, 0))  # (9, P, 3)
    dense = np.einsum("nk,kpc->npc", sh.sh_basis(dirs), irr).min(axis=0) / np.pi
    got = np.asarray(s["sh_min"], np.float64)
    scale = np.abs(coeffs[:, 0]).max()
    assert np.all(got <= dense + 1e-6 * scale)
    np.testing.assert_allclose(got, dense, rtol=0, atol=2e-3 * scale)


class _StopInFinalStage(InlineExecutor):
    """Runs the bake in this process and raises KeyboardInterrupt after the first batch of the
    final stage (the third map of a one-bounce bake), as a Ctrl-C would."""

    def __init__(self) -> None:
        super().__init__(check_pickle=False)
        self.maps = 0

    def map(self, fn, context, batches, *, progress=None):
        self.maps += 1
        for k, item in enumerate(super().map(fn, context, batches, progress=progress)):
            yield item
            if self.maps == 3 and k == 0:
                raise KeyboardInterrupt


def test_an_interrupted_overwrite_bake_resumes_and_a_running_bake_is_never_deleted(tmp_path):
    from probegrid.bake.driver import _bake_lock
    from probegrid.store.manifest import work_path as _work_dir

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 1, 2))
    st = BakeSettings(bounces=1, **{**FAST, "batch_size": 2})
    out = tmp_path / "room.probes"
    bake(_room_scene(), grid, out, settings=st)
    with pytest.raises(KeyboardInterrupt):
        bake(_room_scene(), grid, out, settings=st, overwrite=True, executor=_StopInFinalStage())
    other_batches = st.model_copy(update={"batch_size": 3})  # changes no bit: may resume
    again = bake(_room_scene(), grid, out, settings=other_batches, overwrite=True)
    assert again.resumed_probes == 2  # the batch stored before the interrupt
    fresh = bake(_room_scene(), grid, tmp_path / "fresh.probes", settings=st)
    a, b = _arrays(again.store), _arrays(fresh.store)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    # another bake of the store holds its lock: an --overwrite bake is refused, deletes nothing
    work = _work_dir(tmp_path / "busy.probes")
    work.mkdir()
    (work / "theirs").write_text("in use")
    with (_bake_lock(work, tmp_path / "busy.probes"),
          pytest.raises(StoreError, match="another process is baking")):
        bake(_room_scene(), grid, tmp_path / "busy.probes", settings=st, overwrite=True)
    assert (work / "theirs").read_text() == "in use"


def test_a_sun_patch_is_lit_by_sampling_the_sky_not_read_from_the_probes(tmp_path):
    """Hits are lit by the environment sampled as a light (shadow rays), not through the probes:
    the floor in a roof's shadow reads exactly 0 after one bounce although the probe beside it
    stands in the sun (read through the grid, the patch's light leaked into the shadow), and
    the sunlit floor reads rho E / pi with E the sun's exact irradiance."""
    from probegrid.core.cubemap import direction_to_texel, texel_directions, texel_solid_angles

    b = SceneBuilder()
    rho = 0.5
    floor = b.add_material(Material.diffuse(rho))
    b.add_quad((-10, 0, -10), (0, 0, 20), (20, 0, 0), material=floor)  # faces +Y
    b.add_box((-1, 1, -1), (1.6, 1.1, 1), material=b.add_material(Material.diffuse(0.5)))
    scene = b.build()
    m = 64
    sky = np.zeros((6, m, m, 3), np.float32)
    sky[2, 31:33, 31:33] = 1000.0  # a small sun straight up (+Y)
    grid = GridSpec.from_counts((0, 0.5, 0), (4, 0.5, 0), (3, 1, 1))  # x = 0 (shaded), 2, 4
    st = BakeSettings(bounces=1, relocate=False, store_incoming=True, **FAST)
    s = bake(scene, grid, tmp_path / "sun.probes", settings=st,
             environment=Environment(faces=sky)).store
    inc = np.asarray(s["incoming"])
    # the floor at x = 1.2 (in the roof's shadow) seen from the shaded probe
    face, row, col = direction_to_texel(np.array([1.2, -0.5, 0.0]), FAST["face_size"])
    assert inc[0, face, row, col].max() == 0.0
    # the sunlit floor straight below the probe at x = 4
    d = texel_directions(m)[2, 31:33, 31:33]
    e_sun = 1000.0 * float((texel_solid_angles(m)[2, 31:33, 31:33] * d[..., 1]).sum())
    n = FAST["face_size"]
    below = inc[2, 3, n // 2 - 1:n // 2 + 1, n // 2 - 1:n // 2 + 1]
    np.testing.assert_allclose(below, rho * e_sun / np.pi, rtol=2e-3)


def test_one_bounce_off_a_floor_is_gathered_not_read_from_the_probe(tmp_path):
    """A point light just above a floor, a ceiling above it, one probe between: after one
    bounce the ceiling reads rho / pi (E_direct + E_floor) with E_floor the exact integral of
    the floor's reflected light over its form factor (a polar quadrature here). Gathered at the
    ceiling's hits, the face's mean is within 1.5 %; read from the probe's own irradiance (the
    probe sits nearer the floor's hot spot than the ceiling does) it was 1.97x too bright."""
    from probegrid.core.cubemap import texel_directions

    rho, power, hl, hc, hp = 0.5, 10.0, 0.3, 2.0, 1.0
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(rho))
    b.add_quad((-10, 0, -10), (0, 0, 20), (20, 0, 0), material=m)  # floor, faces +Y
    b.add_quad((-10, hc, -10), (20, 0, 0), (0, 0, 20), material=m)  # ceiling, faces -Y
    b.add_light(PointLight((0.0, hl, 0.0), (1.0, 1.0, 1.0), power))
    n = 16
    grid = GridSpec.from_counts((0, hp, 0), (0, hp, 0), (1, 1, 1))
    st = BakeSettings(face_size=n, diffuse_size=4, moments_size=4, bounces=1, gather_samples=64,
                      relocate=False, store_incoming=True)
    inc = np.asarray(bake(b.build(), grid, tmp_path / "g.probes", settings=st).store["incoming"])
    # the exact value at each +Y texel's ceiling point
    d = texel_directions(n)[2].reshape(-1, 3)
    pts = np.array([0.0, hp, 0.0]) + d * ((hc - hp) / d[:, 1])[:, None]
    e_dir = power * (hc - hl) / np.sum((pts - [0.0, hl, 0.0]) ** 2, axis=1) ** 1.5
    edges = np.concatenate([[0.0], np.geomspace(1e-3, 10.0, 300)])  # rings about the hot spot
    r = 0.5 * (edges[1:] + edges[:-1])
    phi = (np.arange(128) + 0.5) * (2 * np.pi / 128)
    rr, pp = np.meshgrid(r, phi)
    area = (0.5 * (edges[1:] ** 2 - edges[:-1] ** 2))[None, :] * (2 * np.pi / 128)
    fx, fz, da = (rr * np.cos(pp)).ravel(), (rr * np.sin(pp)).ravel(), np.broadcast_to(
        area, rr.shape).ravel()
    d2 = fx ** 2 + hl ** 2 + fz ** 2
    radiance = rho * power * hl / d2 ** 1.5 / np.pi  # the floor's reflected light
    vx, vz = fx[None, :] - pts[:, :1], fz[None, :] - pts[:, 2:]
    r2 = vx ** 2 + vz ** 2 + hc ** 2
    e_floor = (radiance * da * (hc * hc) / r2 ** 2).sum(axis=1)  # cos cos / r^2
    exact = rho / np.pi * (e_dir + e_floor)
    got = inc[0, 2].reshape(-1, 3)
    assert float(np.mean(e_floor / (e_dir + e_floor))) > 0.3  # the bounce is a third of it
    np.testing.assert_allclose(got.mean(axis=0), exact.mean(), rtol=0.015)


def test_the_gathers_noise_is_spread_over_texels_without_changing_what_they_hold(
        tmp_path, monkeypatch):
    """What a probe sees of its hits' gathered light keeps the grid read at each hit and the
    gather's correction smoothed over the texels around it: two seeds differ by 3.3 % per
    texel (2.7 % with a mean correction per 8 x 8 block and rays through the texel centres,
    which every seed shares; 9 % with the raw gather), and each probe's solid-angle integral
    over the hits facing each side (floor, ceiling, each wall) is what the raw gather gives: no
    light moves between surfaces."""
    from probegrid.bake.records import replay as rc
    from probegrid.core.arrays import sum_rows
    from probegrid.core.cubemap import texel_solid_angles

    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.7))
    b.add_box((-2, 0, -2), (2, 3, 2), material=m, inward=True)
    b.add_light(PointLight((0.5, 2.5, 0.3), (1.0, 1.0, 1.0), 20.0))
    scene = b.build()
    grid = GridSpec.from_counts((-1, 0.75, -1), (1, 2.25, 1), (2, 2, 2))
    original = rc._smooth_gathered
    integrals = []

    def checked(records, settings, rad, *args):
        out = original(records, settings, rad, *args)
        n = settings.face_size
        sa = np.tile(texel_solid_angles(n).reshape(-1), len(records.probes))
        probe = np.arange(len(sa)) // (6 * n * n)
        rays = records.levels[0]
        nrm = rays.normal
        axis = np.argmax(np.abs(nrm), axis=1)
        side = 2 * axis + (nrm[np.arange(len(nrm)), axis] > 0)
        key = probe * 6 + np.where(rays.kind == 1, side, 0)
        assert len(np.unique(side[rays.kind == 1])) == 6  # all six sides seen
        integrals.append((sum_rows(key, sa[:, None] * rad, 6 * (probe.max() + 1)),
                          sum_rows(key, sa[:, None] * out, 6 * (probe.max() + 1))))
        return out

    monkeypatch.setattr(rc, "_smooth_gathered", checked)
    incoming = []
    for seed in (0, 1):
        st = BakeSettings(face_size=16, diffuse_size=4, moments_size=4, bounces=3, seed=seed,
                          store_incoming=True)  # (bounce 3 reads the grid of bounce 0)
        s = bake(scene, grid, tmp_path / f"s{seed}.probes", settings=st).store
        incoming.append(np.asarray(s["incoming"], np.float64))
    assert integrals
    for before, after in integrals:
        np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-6 * before.max())
    a, c = incoming
    assert np.abs(a - c).sum() / (a + c).sum() < 0.04


def test_environment_rotation_rotates_the_probes(tmp_path):
    from probegrid.core.sh import rotate_y

    rng = np.random.default_rng(1)
    faces = rng.random((6, 16, 16, 3)).astype(np.float32) + np.linspace(0, 2, 16)[:, None, None]
    scene = _lone_light_scene(intensity=0.0)
    grid = GridSpec.from_counts((0, 0, 0), (0, 0, 0), (1, 1, 1))
    st = BakeSettings(bounces=0, face_size=32, diffuse_size=4, moments_size=4, samples=4)
    plain = bake(scene, grid, tmp_path / "a.probes", settings=st,
                 environment=Environment(faces=faces)).store
    turned = bake(scene, grid, tmp_path / "b.probes", settings=st,
                  environment=Environment(faces=faces, rotation=np.pi / 2, intensity=2.0)).store
    expected = 2.0 * rotate_y(np.asarray(plain["sh"][0], np.float64), np.pi / 2)
    np.testing.assert_allclose(turned["sh"][0], expected, atol=0.02 * abs(expected[0]).max())


# ------------------------------------------------------------- emitters, gather, bounces, stages
def _rectangle_form_factor(a: float, b: float, c: float) -> float:
    """Form factor from a point to a parallel ``a x b`` rectangle centred on its normal at
    distance ``c`` (four corner rectangles of the classic closed form, Howell's catalogue C-11)."""
    x, y = a / 2 / c, b / 2 / c
    f = (x / np.hypot(1, x) * np.arctan(y / np.hypot(1, x))
         + y / np.hypot(1, y) * np.arctan(x / np.hypot(1, y))) / (2 * np.pi)
    return 4 * f


def test_a_panel_smaller_than_a_texel_keeps_its_energy_at_one_ray_per_texel(tmp_path):
    """A 0.06-unit emissive square 2 units above a probe, centred where 4 texels of an 8^2 cube
    meet (no texel centre ray hits it): the probe's cube carries its exact solid angle times
    its radiance, and the irradiance toward it matches the exact polygon form factor."""
    from probegrid.core.cubemap import texel_directions, texel_solid_angles

    le, a, c = 50.0, 0.06, 2.0
    b = SceneBuilder()
    m = b.add_material(Material(base_color=(0.5, 0.5, 0.5), emissive=(le, le, le)))
    b.add_quad((-a / 2, c, -a / 2), (a, 0, 0), (0, 0, a), material=m)  # faces -Y
    scene = b.build()
    assert np.allclose(scene.triangle_normals, [0, -1, 0])
    grid = GridSpec.from_counts((0, 0, 0), (0, 0, 0), (1, 1, 1))
    st = BakeSettings(bounces=0, store_incoming=True, **FAST)
    s = bake(scene, grid, tmp_path / "panel.probes", settings=st).store
    cube = np.asarray(s["incoming"][0], np.float64)[..., 0]
    omega = 4 * np.arcsin(a * a / (a * a + 4 * c * c))  # solid angle of the centred square
    energy = float(np.sum(cube * texel_solid_angles(8)))
    assert energy == pytest.approx(le * omega, rel=1e-4)
    d = texel_directions(8)
    e_over_pi = float(np.sum(cube * np.maximum(d[..., 1], 0) * texel_solid_angles(8))) / np.pi
    assert e_over_pi == pytest.approx(le * _rectangle_form_factor(a, a, c), rel=0.02)


def test_cornell_ceiling_reads_zero_after_one_bounce(tmp_path, real_data):
    """The CornellBox's ceiling sits behind its emitting panel's plane: after one bounce (light
    reflected once) it is black. Light from the panel reaches the walls by next-event
    estimation, the grid carries no emission and cannot ring, so nothing leaks onto it."""
    glb = real_data / "gltf" / "CornellBox.glb"
    from probegrid.bake.pattern import sample_pattern
    from probegrid.raytrace import RayTracer
    from probegrid.scene import load_gltf

    scene = load_gltf(glb)
    lo, hi = scene.bounds
    centre = (lo + hi) / 2
    grid = GridSpec.from_counts(centre - (hi - lo) * 0.25, centre + (hi - lo) * 0.25, (2, 2, 2))
    st = BakeSettings(bounces=1, store_incoming=True, face_size=16, diffuse_size=4,
                      moments_size=4)
    s = bake(scene, grid, tmp_path / "cornell.probes", settings=st).store
    emissive = np.array([mm.emissive.max() > 0 for mm in scene.materials])[scene.material]
    panel = scene.vertices[scene.triangles[emissive]].reshape(-1, 3)
    margin = 0.1 * (hi - lo)[0]
    tracer = RayTracer.from_scene(scene)
    checked = 0
    for p in range(grid.n_probes):
        d = sample_pattern(st)[0].reshape(-1, 3)  # the probe's own rays, one per texel
        pos = np.asarray(s["positions"][p])
        hits = tracer.intersect(np.repeat(pos[None], len(d), 0), d)
        pt = pos + hits.t[:, None] * d
        ceiling = (hits.prim_id >= 0) & (pt[:, 1] > hi[1] - 1e-3 * (hi - lo)[1])
        ceiling &= ~emissive[np.maximum(hits.prim_id, 0)]
        near_panel = np.all((pt[:, [0, 2]] > panel[:, [0, 2]].min(0) - margin)
                            & (pt[:, [0, 2]] < panel[:, [0, 2]].max(0) + margin), axis=1)
        sel = ceiling & ~near_panel
        cube = np.asarray(s["incoming"][p]).reshape(-1, 3)
        assert np.all(cube[sel] == 0.0), p
        assert cube.max() > 0
        checked += int(sel.sum())
    assert checked > 50


@pytest.mark.parametrize("depth", [2, 3])
def test_converged_bounces_match_the_furnace_series(tmp_path, depth):
    """``bounces="converge"`` stops when the estimated limit of the grid's energy changes by
    less than the tolerance and extrapolates the grid to it: a closed furnace box, a pure
    geometric series, reads ``Le / (1 - rho)`` within 1e-4 (SH; the 8^2 diffuse map within its
    quadrature's 1e-3), ten times closer than the fixed bounce count it ran; the ratio of one
    grid level to the next it found is ``rho^(depth + 1)`` (the gather rays' deepest hits read
    the grid ``depth + 1`` levels down); the manifest records all of it."""
    rho, le = 0.5, 2.0
    scene = box_scene((-1, -1, -1), (1, 1, 1), albedo=rho, emission=le, inward=True)
    grid = GridSpec.from_counts((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), (2, 1, 1))
    st = BakeSettings(bounces="converge", gather_depth=depth, **FAST)
    report = bake(scene, grid, tmp_path / "f.probes", settings=st)
    q = report.store.manifest.quality
    limit = le / (1 - rho)
    np.testing.assert_allclose(report.store["diffuse"], limit, rtol=1e-3)  # the quadrature
    np.testing.assert_allclose(report.store["sh"][:, 0], 2 * np.sqrt(np.pi) * limit, rtol=1e-4)
    step = rho ** (depth + 1)
    np.testing.assert_allclose(q["bounce_extrapolation"], step / (1 - step), rtol=1e-3)
    assert q["bounce_passes"] == q["bounces"] - (depth + 1)
    assert 7 <= q["bounce_passes"] < st.max_bounces
    assert 0 <= q["bounce_residual"] < st.tolerance
    assert q["bounce_energy_limit"] > q["bounce_energy"][-1]
    fixed = bake(scene, grid, tmp_path / "g.probes",
                 settings=BakeSettings(bounces=q["bounces"], gather_depth=depth, **FAST)).store
    dc = 2 * np.sqrt(np.pi) * limit
    assert (np.abs(report.store["sh"][:, 0] - dc).max()
            < 0.1 * np.abs(fixed["sh"][:, 0] - dc).max())


@pytest.mark.slow
def test_progress_names_the_bounces(tmp_path):
    scene = box_scene((-1, -1, -1), (1, 1, 1), albedo=0.5, emission=1.0, inward=True)
    grid = GridSpec.from_counts((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), (2, 1, 1))
    stages: list[str] = []

    def note(stage, p, rays):
        if not stages or stages[-1] != stage:
            stages.append(stage)

    bake(scene, grid, tmp_path / "a.probes", settings=BakeSettings(bounces=3, **FAST),
         progress=note)
    # (two gather levels: the final pass at bounce 3 reads the grid of bounce 0; one level:
    # the grid of bounce 1, no pass 2)
    assert stages == ["classify", "bounce 0 of 3 (tracing)", "bounce 3 of 3 (final)"]
    stages.clear()
    bake(scene, grid, tmp_path / "d.probes", settings=BakeSettings(bounces=3, gather_depth=1,
                                                                     **FAST), progress=note)
    assert stages == ["classify", "bounce 0 of 3 (tracing)", "bounce 1 of 3",
                      "bounce 3 of 3 (final)"]
    stages.clear()
    bake(scene, grid, tmp_path / "n.probes", settings=BakeSettings(bounces=3, gather_samples=0,
                                                                     **FAST), progress=note)
    assert stages == ["classify", "bounce 0 of 3 (tracing)", "bounce 1 of 3", "bounce 2 of 3",
                      "bounce 3 of 3 (final)"]
    stages.clear()
    bake(scene, grid, tmp_path / "b.probes", settings=BakeSettings(**FAST), progress=note)
    assert stages[1] == "tracing: bounce 0"
    assert stages[2] == "converging: bounce 1, residual -"
    assert stages[3].startswith("converging: bounce 2, residual ") and stages[3].endswith(" %")
    assert stages[-1].startswith("converged: bounce ") and stages[-1].endswith("(final)")


def test_preload_bakes_its_tiny_scene_and_loads_the_kernels():
    """probegrid.bake.preload (what worker processes import before their first batch) swallows
    its errors, so here its warm-up must run cleanly and leave the bake's kernels compiled."""
    import numba

    from probegrid.bake import preload
    from probegrid.bake.kernels import (
        cube,
        emitters,
        environment,
        grid,
        lights,
        sampling,
        surfaces,
        texels,
    )
    from probegrid.raytrace import kernels as rays

    preload._warm_up()  # raises if the tiny bake fails
    used = [(surfaces, "shade_hits"), (surfaces, "scatter_divided"), (lights, "light_rays"),
            (emitters, "emitter_samples"), (emitters, "emitter_estimate"),
            (emitters, "polygon_irradiance"), (environment, "environment_samples"),
            (sampling, "gather_rays"), (grid, "hit_probe_weights"), (grid, "replay_radiance"),
            (grid, "distance_moments"), (cube, "cube_sample_directions"),
            (emitters, "texel_emitter_coverage"), (rays, "embree_rays"), (rays, "embree_hits"),
            (texels, "smooth_texels")]
    for module, name in used:
        fn = getattr(module, name)
        assert isinstance(fn, numba.core.registry.CPUDispatcher)
        assert fn.signatures, f"{name} was not loaded by the warm-up bake"


def test_a_process_builds_one_record_tracer_per_bake():
    """Every stage of a bake hands its workers the context anew; the record tracer (BVH,
    emitter and environment tables) is built once per process and bake fingerprint."""
    from probegrid.bake import stages

    b = SceneBuilder()
    b.add_box((-1, 0, -1), (1, 2, 1), material=b.add_material(Material.diffuse(0.5)),
              inward=True)
    scene = b.build()
    grid = GridSpec(bounds_min=(-0.5, 1, 0), bounds_max=(0.5, 1, 0), counts=(2, 1, 1))
    st = BakeSettings(face_size=8)
    ctx = stages.StageContext(scene, Environment(color=np.array([1.0, 1.0, 1.0])),
                              st, grid, st.trace_geometry(scene, grid), key="bake-a")
    first = ctx.setup().tracer
    assert dataclasses.replace(ctx, level=3).setup().tracer is first  # a later stage
    assert dataclasses.replace(ctx, key="bake-b").setup().tracer is not first
    assert dataclasses.replace(ctx, key="").setup().tracer is not first  # no key: no sharing


def test_trace_geometry_follows_the_extent_of_the_scene_and_grid():
    """The rays' offset and a miss's distance come from the extent of the scene and grid
    together (the offset setting overrides); a moments cube whose texels would not bin whole
    incoming texels is refused, and one larger than the incoming cube is clamped to it."""
    from probegrid.bake.settings import TraceGeometry

    b = SceneBuilder()
    b.add_box((-1, 0, -1), (1, 2, 1), material=b.add_material(Material.diffuse(0.5)),
              inward=True)
    scene = b.build()
    grid = GridSpec(bounds_min=(-0.5, 1, 0), bounds_max=(3.0, 1, 0), counts=(2, 1, 1))
    extent = float(np.sqrt(4.0**2 + 2.0**2 + 2.0**2))  # x from -1 (box) to 3 (grid)
    geo = BakeSettings(face_size=8).trace_geometry(scene, grid)
    assert geo.ray_offset == pytest.approx(extent * 1e-5, rel=1e-12)
    assert geo.max_distance == pytest.approx(2.0 * extent, rel=1e-12)
    assert BakeSettings(ray_offset=1e-3).trace_geometry(scene, grid).ray_offset == 1e-3
    with pytest.raises(ValueError, match="moments_size 8 must divide face_size 12"):
        BakeSettings(face_size=12).trace_geometry(scene, grid)
    small = BakeSettings(face_size=4, moments_size=8)
    assert small.moments_face_size == 4 and small.environment_footprint == 4
    assert small.trace_geometry(scene, grid).max_distance == geo.max_distance
    with pytest.raises(ValueError, match="ray_offset must be > 0"):
        TraceGeometry(ray_offset=0.0)


class _StopInMap(InlineExecutor):
    """Runs the bake in this process and raises KeyboardInterrupt after the first batch of the
    ``stop``-th map (1: classify, 2: trace, ...), as a Ctrl-C would."""

    def __init__(self, stop: int) -> None:
        super().__init__(check_pickle=False)
        self.stop = stop
        self.maps = 0

    def map(self, fn, context, batches, *, progress=None):
        self.maps += 1
        for k, item in enumerate(super().map(fn, context, batches, progress=progress)):
            yield item
            if self.maps == self.stop and k == 0:
                raise KeyboardInterrupt


@pytest.mark.parametrize("stop", [1, 2, 3])
def test_a_rerun_with_other_settings_after_an_interrupt_starts_clean(tmp_path, stop):
    """The work directory is keyed by the scene and the settings: a bake interrupted in any
    stage, re-run with another grid and other settings (no --overwrite), starts clean and gives
    the bits of a fresh bake; the same settings again resume."""
    st = BakeSettings(bounces=1, **{**FAST, "batch_size": 2})
    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 1, 2))
    other_grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 2, 2))
    other = st.model_copy(update={"face_size": 16})
    out = tmp_path / "room.probes"
    with pytest.raises(KeyboardInterrupt):
        bake(_room_scene(), grid, out, settings=st, executor=_StopInMap(stop))
    again = bake(_room_scene(), other_grid, out, settings=other)
    assert again.resumed_probes == 0
    fresh = bake(_room_scene(), other_grid, tmp_path / "fresh.probes", settings=other)
    a, b = _arrays(again.store), _arrays(fresh.store)
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fresh.probes", "room.probes"]


def test_a_symlinked_work_directory_or_store_is_unlinked_never_emptied(tmp_path):
    """A link at ``NAME.probes.work`` or ``NAME.probes`` is replaced, its target untouched;
    an --overwrite bake leaves no copy of the old store behind."""
    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (2, 1, 2))
    st = BakeSettings(bounces=1, **FAST)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "theirs").write_text("keep")
    out = tmp_path / "room.probes"
    out.with_name("room.probes.work").symlink_to(victim)
    out.symlink_to(victim)
    done = bake(_room_scene(), grid, out, settings=st, overwrite=True)
    assert sorted(p.name for p in victim.iterdir()) == ["theirs"]
    assert (victim / "theirs").read_text() == "keep"
    assert not out.is_symlink() and done.store.grid.n_probes == 4
    # a copy left aside by an interrupted replacement is deleted by the next bake
    stale = tmp_path / "room.probes.replaced-999999"
    stale.mkdir()
    bake(_room_scene(), grid, out, settings=st, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.probes", "victim"]


class _KillAWorkerAtPass:
    """Delegates to a Dask executor and, before the ``at``-th map call (a pass boundary),
    kills one worker process with SIGKILL (its nanny starts a new one)."""

    def __init__(self, executor, at: int) -> None:
        self._ex, self._at, self.calls, self.killed = executor, at, 0, None

    def __getattr__(self, name):
        return getattr(self._ex, name)

    def map(self, fn, context, batches, *, progress=None):
        self.calls += 1
        if self.calls == self._at:
            pids = self._ex.client.run(os.getpid)
            self.killed = pids[sorted(pids)[0]]
            os.kill(self.killed, signal.SIGKILL)
        return self._ex.map(fn, context, batches, progress=progress)


@pytest.mark.slow
@pytest.mark.parametrize("at", [2, 3])
def test_a_dask_bake_survives_a_worker_killed_at_a_pass_boundary(tmp_path, at):
    """A worker lost between passes (its records with it): the bake completes, bit for bit
    the bake of an uninterrupted cluster."""
    distributed = pytest.importorskip("distributed")
    from probegrid.bake.executors import DaskExecutor

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 2, 2))
    st = BakeSettings(bounces=2, samples=2, seed=7, **FAST)
    ref = _arrays(bake(_room_scene(), grid, tmp_path / "ref.probes", settings=st).store)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        ex = DaskExecutor(cluster.scheduler_address, timeout=30)
        try:
            killer = _KillAWorkerAtPass(ex, at)
            got = bake(_room_scene(), grid, tmp_path / "dask.probes", settings=st,
                       executor=killer)
        finally:
            ex.close()
    assert killer.killed is not None
    a = _arrays(got.store)
    for k in ref:
        assert np.array_equal(a[k], ref[k]), k


class _KillAWorkerInPass(_KillAWorkerAtPass):
    """Kills one worker *during* the ``at``-th map call: after its first batch came back, while
    the pass's other batches are queued or running (and the worker may hold the context)."""

    def map(self, fn, context, batches, *, progress=None):
        self.calls += 1
        results = self._ex.map(fn, context, batches, progress=progress)
        return self._killing(results) if self.calls == self._at else results

    def _killing(self, results):
        self.after = 0
        for i, item in enumerate(results):
            if i == 1:
                self.after = 1
            elif i > 1:
                self.after += 1
            yield item
            if i == 0:
                pids = self._ex.client.run(os.getpid)
                self.killed = pids[sorted(pids)[0]]
                os.kill(self.killed, signal.SIGKILL)


@pytest.mark.slow
@pytest.mark.parametrize("at", [1, 2])
def test_a_dask_bake_survives_a_worker_killed_during_a_pass(tmp_path, at):
    """A worker killed in the middle of a pass (the first batch back, the others queued or
    running, the context possibly on it): the lost tasks are computed again and the bake is
    bit for bit the inline bake."""
    distributed = pytest.importorskip("distributed")
    from probegrid.bake.executors import DaskExecutor

    grid = GridSpec.from_counts((-1.5, 0.5, -1.5), (1.5, 2.5, 1.5), (3, 2, 2))
    st = BakeSettings(bounces=2, samples=2, seed=7, **{**FAST, "batch_size": 2})  # 6 batches a pass
    ref = _arrays(bake(_room_scene(), grid, tmp_path / "ref.probes", settings=st).store)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        ex = DaskExecutor(cluster.scheduler_address, timeout=30)
        try:
            killer = _KillAWorkerInPass(ex, at)
            got = bake(_room_scene(), grid, tmp_path / "dask.probes", settings=st,
                       executor=killer)
        finally:
            ex.close()
    assert killer.killed is not None and killer.after > 0  # batches came back after the kill
    a = _arrays(got.store)
    for k in ref:
        assert np.array_equal(a[k], ref[k]), k
