"""Trace once, replay every bounce: per-hit records of a batch of probes.

A bake's bounces differ only in the light its grid carries, never in its rays. So each probe's
rays are cast once (:meth:`RecordTracer.trace`: the primary rays, the shadow rays toward the
punctual lights and toward points sampled on the emitters at every hit, the probe's own rays
toward the lights and the emitter pieces of its direct view) and what a bounce needs of each
ray is kept as a record:

* ``kind`` -- 0 a miss, 1 a front hit, 2 a back hit (black);
* ``emission`` -- the radiance the surface emits toward the probe (front of an emitter only,
  :mod:`probegrid.bake.emitters`);
* ``light_punctual`` -- for a miss the environment's radiance; for a hit the punctual lights'
  shadowed irradiance / pi;
* ``light_emitters`` -- the direct irradiance / pi at the hit from the emitters (next-event
  estimation with an exact control variate) and from the environment (sampled as a light,
  :class:`probegrid.bake.environment.EnvironmentLight`);
* ``albedo``, ``position``, ``normal`` -- the hit (normal turned toward the probe);

and, per probe, the correction of its direct view of the emitters (exact texel coverage) and
the punctual lights it sees (folded in at the end, :func:`probegrid.core.lights.splat_delta`).
Once every probe's distance moments are known, each hit's 8 surrounding probes and their DDGI
weights are computed once (:func:`probegrid.bake.kernels.grid.hit_probe_weights`) and kept
beside the records. A bounce is then a pass over the records (:func:`replay`,
:func:`probegrid.bake.kernels.grid.replay_radiance`) that reads only the grid's small per-probe
data: each probe's irradiance cube of the previous bounce.

Final gather
------------
Each front hit also casts ``gather_samples`` cosine-weighted rays (``gather_*`` records,
:func:`probegrid.bake.kernels.sampling.gather_rays`), traced once and lit as the probe's rays are
(punctual lights, one emitter and one environment sample at their hits; their misses and
emission count 0: the
environment and the emitters reach the hit by sampling), and with ``gather_depth = 2`` (the
default) each of their hits casts one more (``gather2_*``; ``gather3_*`` one level further with
3). A bounce at level ``k`` reads the
grid at the deepest level's hits, for the light they reflect at level ``k - depth``, i.e. the
grid of level ``k - 1 - depth`` (:func:`grid_level_read`); each level's mean radiance is the
level above's irradiance / pi. (On the sample room against a path tracer: 1.59 % mean error
with one level, 0.99 % with two, for about 15 % more bake time; 0.77 % with three, for 1.4x
the converged bake's CPU time: the grid read at the deepest hits is what remains biased, up to
1.5 % bright for the probes by a wall.)
The probes' irradiance interpolated between them is then one reflection further from what is
seen: read at the hit itself, it is the irradiance where the probes stand, not where the hit
is (a ceiling above a floor's hot spot read a probe nearer the spot: 1.97x too bright;
``tests/test_bake.py``). ``gather_samples = 0`` reads the grid at the hit. What the probe
itself finally sees of that light is the grid read at each hit plus the gather's mean
correction over blocks of texels (:func:`_smooth_gathered`): the integrals are the gather's,
the per-texel noise a quarter of it.

What the grid carries
---------------------
Only light that has been reflected at least once: the ``bounced`` radiance of a ray leaves out
the emission of the surface it hits and, for a miss, the environment. Direct light reaches hits
from the emitters and the environment by explicit sampling and from punctual lights by shadow
rays, so no light is counted twice, and none of it is interpolated between probes (a sun patch
read through the probes leaked into the shadows beside it). A hit reads the grid through each surrounding probe's own irradiance cube (the
exact clamped-cosine convolution of its bounced radiance, :func:`irradiance_size`-texel faces,
looked up bilinearly at the normal): a weighted mean of non-negative irradiances, which cannot
go negative or ring around a small bright source the way 9 SH coefficients do.

Bounce levels (as before this module: ``bounces = B`` makes a furnace box read
``Le (1 - rho^(B+1)) / (1 - rho)``): at level 0 a hit returns its emission and the punctual
lights' reflected light; at level ``k > 0`` it adds the emitters' and the environment's
reflected direct light and the level ``k - 1`` grid.

Records live in a directory per block of probes (the fixed batch partition), one ``.npy`` per
array, written atomically by the worker that traced them (the ``complete`` mark last); the
worker also keeps the blocks it used last in memory (:data:`RECORDS_MEMORY`), and any other
block is memory-mapped from its files, so a pass over a block reads only that block and a
worker's memory is bounded by its batch. A bake's only worker process (no other process will
ask for its blocks) keeps them in memory alone and writes a block only when the bound pushes
it out (``save_records(files=False)``). A gather level keeps only what later passes read
(:func:`_gather_keys`; the deepest level's positions go once its probe weights are known,
:func:`weighted_positions`): :func:`record_bytes` gives the bake's estimate. A block whose
files are missing (a Dask worker on another machine, a file deleted) is traced again: the
records are deterministic, so the result is the same bits.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.emitters import Emitters
from probegrid.bake.environment import Environment, EnvironmentLight
from probegrid.bake.kernels.cube import CUBE_AXES
from probegrid.bake.kernels.grid import (
    GridLattice,
    ProbeTable,
    ReplayRecords,
    Weighting,
    distance_moments,
    hit_probe_weights,
    mean_per_parent,
    replay_radiance,
    texel_means,
)
from probegrid.bake.kernels.lights import light_rays, sum_unblocked
from probegrid.bake.kernels.sampling import gather_rays, stream_uniforms
from probegrid.bake.kernels.surfaces import HitRecords, scatter_divided, shade_hits
from probegrid.bake.render import SHADE_CHUNK, ProbeRenderer, RenderSettings, sample_pattern
from probegrid.core.arrays import one_blas_thread, sum_rows
from probegrid.core.cubemap import (
    direction_to_face,
    downsample,
    texel_directions,
    texel_solid_angles,
)
from probegrid.core.ddgi import (
    CRUSH_THRESHOLD,
    DEFAULT_NORMAL_BIAS,
    MIN_WEIGHT,
    NORMAL_TERM_FLOOR,
)
from probegrid.core.grid import CORNER_OFFSETS, GridSpec
from probegrid.core.lights import splat_delta
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.scene import Scene

__all__ = [
    "RECORDS_MEMORY",
    "RecordTracer",
    "irradiance_cubes",
    "irradiance_size",
    "record_bytes",
    "records_file",
    "replay",
]

def irradiance_size(gather: bool) -> int:
    """Face size of the per-probe irradiance cubes hits read the grid through: 16 when the hits
    read them at their own normal; 8 when gather rays' hits read them (one reflection further
    from what the probes see: on the sample room against a path tracer, 2.28 % mean error at 8,
    2.30 % at 16)."""
    return 8 if gather else 16

_RECORD_KEYS = ("kind", "emission", "light_punctual", "light_emitters", "albedo", "position",
                "normal")


def _gather_keys(*, deepest: bool) -> tuple[str, ...]:
    """What a gather level keeps of its records: no emission (its hits' emission counts 0: the
    emitters reach the hit above by sampling), and positions and normals only at the deepest
    level, whose hits read the grid (the positions until their probe weights are known,
    :func:`all_hit_weights`)."""
    keep = ("kind", "light_punctual", "light_emitters", "albedo")
    return keep + ("position", "normal") if deepest else keep


#: Key prefix of each level's records: the probes' rays, then each gather level (the rays of
#: level ``d`` name their parent hit of level ``d - 1`` in ``PREFIX + "primary"``).
_LEVELS = ("", "gather_", "gather2_", "gather3_")


def gather_depth(records: dict[str, NDArray[Any]]) -> int:
    """Gather levels the records hold: 0 (none), 1 (``gather_*``), 2 (``gather2_*`` too) or 3
    (``gather3_*`` too)."""
    return sum(1 for prefix in _LEVELS[1:] if prefix + "primary" in records)


#: Random numbers for given rows (a probe stream's rows, see RecordTracer.trace).
Draw = Callable[[NDArray[np.int64]], NDArray[np.float64]]


def _light_draw(draw: Callable[[int, int, int, NDArray[np.int64]], NDArray[np.float64]],
                purpose: int, per: int, samples: int) -> Draw | None:
    """The random numbers of ``samples`` light samples per ray (3 each: :meth:`RecordTracer.trace`'s
    ``draw`` of one purpose, ``per`` rays per probe) as a :data:`Draw` of ``(k, samples, 3)``;
    None for no sample."""
    if not samples:
        return None
    return lambda rows: draw(purpose, per, samples * 3, rows).reshape(-1, samples, 3)


def _new_records(k: int) -> dict[str, NDArray[Any]]:
    """Empty records (:data:`_RECORD_KEYS`) of ``k`` rays: misses."""
    return {
        "kind": np.zeros(k, np.uint8),
        "emission": np.zeros((k, 3), np.float32),
        "light_punctual": np.zeros((k, 3), np.float32),
        "light_emitters": np.zeros((k, 3), np.float32),
        "albedo": np.zeros((k, 3), np.float32),
        "position": np.zeros((k, 3), np.float64),
        "normal": np.zeros((k, 3), np.float32),
    }


def record_bytes(primary: int, gather_samples: int, depth: int) -> int:
    """Bytes the records of ``primary`` probe rays take at most (every ray a front hit, every
    gather level full), their probe weights included: the probes' rays keep every
    :data:`_RECORD_KEYS` array; each gather level (``gather_samples`` rays per primary ray)
    what :func:`_gather_keys` keeps plus its 32-bit parent rows; the level whose hits read the
    grid also its weights (8 int32 probes and 8 float32 weights)."""
    size = {k: v.itemsize * (v.shape[1] if v.ndim > 1 else 1)
            for k, v in _new_records(1).items()}
    weights = 8 * (4 + 4)
    total = primary * sum(size[k] for k in _RECORD_KEYS)
    if depth == 0 or gather_samples == 0:
        return total + primary * weights
    for d in range(1, depth + 1):
        deepest = d == depth
        per_ray = (sum(size[k] for k in _gather_keys(deepest=deepest)) + 4
                   + (weights if deepest else 0))
        total += primary * gather_samples * per_ray
    return total


def _stream_keys(seed: int, indices: NDArray[np.int64], purpose: int) -> NDArray[np.uint64]:
    """The keys of the probes' random streams for one purpose (independent of the sample
    pattern's): 64 bits of ``SeedSequence(seed, spawn_key=(index, purpose))`` each, for
    :func:`probegrid.bake.kernels.sampling.stream_uniforms`."""
    return np.array([np.random.SeedSequence(int(seed), spawn_key=(int(i), purpose))
                     .generate_state(1, np.uint64)[0] for i in indices], np.uint64)


@lru_cache(maxsize=4)
def _irradiance_matrix(n: int, g: int) -> NDArray[np.float32]:
    """``(6 g^2, 6 n^2)`` float32: irradiance / pi at the ``g``-cube's texel directions of an
    ``n``-cube of radiance (the clamped-cosine sum of :func:`probegrid.core.diffuse.diffuse_exact`,
    each row normalised to sum to 1)."""
    out = texel_directions(g).reshape(-1, 3)
    src = texel_directions(n).reshape(-1, 3)
    m = np.maximum(out @ src.T, 0.0) * texel_solid_angles(n).reshape(1, -1)
    # each row normalised to sum to 1 (the clamped cosine / pi integrates to 1): a constant
    # radiance gives exactly itself, as the furnace requires, whatever n
    m = (m / m.sum(axis=1, keepdims=True)).astype(np.float32)
    m.setflags(write=False)
    return m


def irradiance_cubes(cubes: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    """Irradiance / pi cubes ``(B, 6, size, size, 3)`` of radiance cubes ``(B, 6, n, n, 3)``
    (box-filtered to ``max(size, 16)`` first when larger: the clamped cosine is smooth at that
    scale),
    8 probes per product, zero-padded to a fixed shape (the bits do not depend on the batch)."""
    b, _, n0, _, _ = cubes.shape
    n = n0
    while n > max(size, 16) and n % 2 == 0:  # the source box-filtered down to 16 (or the output)
        n //= 2
    mat = _irradiance_matrix(n, size)
    out = np.empty((b, 6, size, size, 3), np.float32)
    group = 8
    for g0 in range(0, b, group):  # groups of probes as the columns of one fixed-shape product
        k = min(group, b - g0)
        stacked = np.zeros((6, n0, n0, group * 3), np.float32)
        stacked[..., :3 * k] = np.moveaxis(cubes[g0:g0 + k], 0, 3).reshape(6, n0, n0, 3 * k)
        while stacked.shape[1] > n:
            stacked = downsample(stacked)
        with one_blas_thread():  # small: threads only spin
            res = mat @ stacked.reshape(6 * n * n, group * 3)  # (6 size^2, group * 3)
        out[g0:g0 + k] = np.moveaxis(res[:, :3 * k].reshape(-1, k, 3), 1, 0).reshape(
            k, 6, size, size, 3)
    return out


def records_file(directory: str | Path, block: int) -> Path:
    """The record directory of the block starting at probe ``block``."""
    return Path(directory) / f"records_{block:09d}"


def resolve_directory(directory: str) -> Path:
    """A records directory: an absolute path as is; a bare name under this machine's
    temporary directory (for workers that do not share the bake's files)."""
    p = Path(directory)
    return p if p.is_absolute() else Path(tempfile.gettempdir()) / directory


def _atomic_npy(path: Path, array: NDArray[Any]) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npy")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


#: Bytes of records a worker process keeps in memory between passes (the blocks it used last;
#: the files stay the reference: a block it does not hold is read back).
RECORDS_MEMORY = 256 << 20

_held: OrderedDict[tuple[str, str], tuple[dict[str, NDArray[Any]], int]] = OrderedDict()
_held_bytes = [0]
_held_lock = threading.Lock()
#: Blocks this process holds without files (``save_records(files=False)``): directory -> token.
_memory_only: dict[str, str] = {}


def _mark(path: Path) -> tuple[str, str] | None:
    """A block's identity: its directory and the random token its ``complete`` mark holds (a
    later bake of the same store writes a new token, so what a process holds of an earlier
    one is never taken for it)."""
    try:
        return (str(path), (path / "complete").read_text())
    except OSError:
        return None


def _nbytes(records: dict[str, NDArray[Any]]) -> int:
    return sum(np.asarray(v).nbytes for v in records.values())


def _held_get(key: tuple[str, str]) -> dict[str, NDArray[Any]] | None:
    with _held_lock:
        item = _held.get(key)
        if item is None:
            return None
        _held.move_to_end(key)
        return item[0]


def _write_block(path: Path, records: dict[str, NDArray[Any]], token: str | None) -> None:
    """One ``.npy`` per array into the directory ``path``, each atomically, then the
    ``complete`` mark (``token``, a new one when None) last: a killed worker leaves no half
    block. Arrays already there when the mark is (the same bits) are not written again."""
    path.mkdir(parents=True, exist_ok=True)
    done = (path / "complete").is_file()
    for k, v in records.items():
        f = path / f"{k}.npy"
        if not (done and f.is_file()):
            _atomic_npy(f, np.asarray(v))
    if not done:
        (path / "complete").write_text(token or os.urandom(8).hex())


def _hold(key: tuple[str, str], records: dict[str, NDArray[Any]]) -> None:
    """Keep ``records`` (its size as it is now) as the most recently used block. A block held
    without files that has to go (the least recently used beyond :data:`RECORDS_MEMORY`) is
    written to its directory first (spilled): what a pass reads is always somewhere. (Unless the
    directory's bake directory is gone: a later pass would trace it again.)"""
    with _held_lock:
        old = _held.pop(key, None)
        if old is not None:
            _held_bytes[0] -= old[1]
        size = _nbytes(records)
        if size > RECORDS_MEMORY:  # larger than all it may hold: not held
            _spill(key, records)
            return
        _held[key] = (records, size)
        _held_bytes[0] += size
        while _held_bytes[0] > RECORDS_MEMORY and _held:  # the least recently used go first
            gone, (old_records, nbytes) = _held.popitem(last=False)
            _held_bytes[0] -= nbytes
            _spill(gone, old_records)


def _spill(key: tuple[str, str], records: dict[str, NDArray[Any]]) -> None:
    """A block leaving this process's memory (``_held_lock`` held): if it was held without
    files, written to its directory now (unless its bake's directory is gone)."""
    where, token = key
    if _memory_only.get(where) != token:
        return  # (its files are the reference)
    del _memory_only[where]
    if Path(where).parent.parent.is_dir():
        shutil.rmtree(where, ignore_errors=True)  # (files of an earlier bake)
        _write_block(Path(where), records, token)


def _drop(path: Path) -> None:
    with _held_lock:
        _memory_only.pop(str(path), None)
        for key in [k for k in _held if k[0] == str(path)]:
            _held_bytes[0] -= _held.pop(key)[1]


def save_records(path: Path, records: dict[str, NDArray[Any]], *,
                 drop: tuple[str, ...] = (), files: bool = True) -> None:
    """Keep a block's ``records`` for the later passes, and the arrays of ``drop`` no more
    (what no later pass reads).

    With ``files`` the arrays go into the directory ``path`` (:func:`_write_block`: atomic, the
    ``complete`` mark last), which any process of the machine can read, and this process keeps
    them in memory too (:data:`RECORDS_MEMORY`). Without, when no other process will ask for
    the block (a bake's only worker process), this process keeps them in memory alone and
    writes them only if they have to leave it (:func:`_hold`). Arrays added to a block (its
    probe weights, say) go where the block is."""
    sp = str(path)
    with _held_lock:
        token = _memory_only.get(sp)
    if token is None and not files:  # a new block in memory alone
        shutil.rmtree(path, ignore_errors=True)  # (files of an earlier bake)
        token = os.urandom(8).hex()
        with _held_lock:
            _memory_only[sp] = token
        _hold((sp, token), records)
        return
    if token is not None:  # a block held without files: added to and dropped from in memory
        key = (sp, token)
        held = _held_get(key)
        if held is not None:
            if held is not records:
                held.update(records)
            for k in drop:
                held.pop(k, None)
            _hold(key, held)
            return
    done = (path / "complete").is_file()
    _write_block(path, records, None)
    for k in drop:
        (path / f"{k}.npy").unlink(missing_ok=True)
    key = _mark(path)
    if key is None:
        return
    if not done:  # a new block
        _hold(key, records)
        return
    held = _held_get(key)
    if held is not None:  # arrays added to a block this process holds
        if held is not records:
            held.update(records)
        for k in drop:
            held.pop(k, None)
        _hold(key, held)


def load_records(path: Path) -> dict[str, NDArray[Any]] | None:
    """The records in the directory ``path`` (one block: memory bounded by the batch), from
    this process's memory when it holds them, else memory-mapped from their files; None when
    there is no complete record."""
    sp = str(path)
    with _held_lock:  # (a block held without files is spilled under this lock)
        token = _memory_only.get(sp)
        item = None if token is None else _held.get((sp, token))
        if item is not None:
            _held.move_to_end((sp, token))
            return item[0]
    key = _mark(path)
    if key is None:
        return None
    held = _held_get(key)
    if held is not None:
        return held
    try:  # memory-mapped: the page cache holds them, no copy (nothing to hold here)
        out = {f.stem: np.load(f, allow_pickle=False, mmap_mode="r").view(np.ndarray)
               for f in path.glob("*.npy") if not f.name.startswith(".")}
    except (OSError, ValueError):
        return None
    return out


def remove_records(path: Path) -> None:
    """Delete a block's records (its last use)."""
    _drop(path)
    shutil.rmtree(path, ignore_errors=True)


def select_probes(records: dict[str, NDArray[Any]], probes: NDArray[np.int64]
                  ) -> dict[str, NDArray[Any]] | None:
    """The records of ``probes`` (a subset of the block's, in order), or None if absent."""
    have = records["probes"]
    if np.array_equal(have, probes):
        return records
    rows = np.searchsorted(have, probes)
    if np.any(rows >= len(have)) or not np.array_equal(have[np.minimum(rows, len(have) - 1)],
                                                       probes):
        return None
    r = int(records["rays_per_probe"])
    ray_rows = (rows[:, None] * r + np.arange(r)[None, :]).reshape(-1)
    out: dict[str, NDArray[Any]] = {"probes": probes, "rays_per_probe": records["rays_per_probe"]}
    if "sky_sampled" in records:
        out["sky_sampled"] = records["sky_sampled"]
    for k in (*_RECORD_KEYS, "weight_index", "weight"):
        if k in records:
            out[k] = records[k][ray_rows]
    kept, parents = ray_rows, len(records["kind"])
    for prefix in _LEVELS[1:gather_depth(records) + 1]:  # each level's rays of kept parents
        new_row = np.full(parents, -1, np.int64)
        new_row[kept] = np.arange(len(kept))
        mapped = new_row[records[prefix + "primary"]]
        rows_k = np.flatnonzero(mapped >= 0)
        for k in records:
            if k.startswith(prefix) and k != prefix + "primary":
                out[k] = records[k][rows_k]
        out[prefix + "primary"] = mapped[rows_k].astype(np.int32)
        kept, parents = rows_k, len(records[prefix + "kind"])
    for k in ("backface_fraction",):
        out[k] = records[k][rows]
    for k, off in (("view", "view_offsets"), ("lights", "lights_offsets")):
        offsets = records[off]
        parts = [np.arange(offsets[i], offsets[i + 1]) for i in rows]
        sel = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        counts = np.array([len(p) for p in parts], np.int64)
        out[off] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        for name in records:
            if name.startswith(k + "_") and name != off:  # (the offsets are the new ones)
                out[name] = records[name][sel]
    return out


class RecordTracer:
    """Traces batches of probes into records (build once per worker: it owns the BVH)."""

    def __init__(self, scene: Scene, environment: Environment, settings: RenderSettings, *,
                 light_samples: int = 2, gather_samples: int = 0, gather_depth: int = 1,
                 tracer: RayTracer | None = None) -> None:
        self.renderer = ProbeRenderer(scene, environment, settings, tracer=tracer)
        self.scene = scene
        self.settings = settings
        self.tracer = self.renderer.tracer
        self.emitters = Emitters.from_scene(scene)
        self.sky = EnvironmentLight(environment)
        self.light_samples = int(light_samples)
        self.gather_samples = int(gather_samples)
        self.gather_depth = int(gather_depth)

    def _shade(self, origins: NDArray[np.float64], dirs: NDArray[np.float64],
               draw_rows: NDArray[np.int64], draw_e: Draw | None, draw_s: Draw | None,
               rec: dict[str, NDArray[Any]], t: NDArray[np.float64], *, sky_at_misses: bool
               ) -> int:
        """Fills ``rec`` (:data:`_RECORD_KEYS`, zeros: misses) and ``t`` with the records and hit
        distances of one chunk of rays; returns the rays cast: the rays themselves and every
        shadow ray of their front hits (punctual lights; ``draw_e(rows) (k, L, 3)`` the random
        numbers of points on the emitters, ``draw_s`` of directions of the environment, None for
        none; ray ``i``'s are row ``draw_rows[i]``, drawn for the front hits only). A miss keeps
        the environment's radiance when ``sky_at_misses`` (what a probe sees), else 0 (the
        environment reaches hits by sampling)."""
        st = self.settings
        rd = self.renderer
        eps = st.ray_offset
        k = len(dirs)
        hits = self.tracer.intersect(origins, dirs)
        rays = k
        sc = self.scene
        # the records of the chunk in one pass: kind, distance, and at each front hit its
        # surface (the normal turned toward the ray: the side it sees is shaded; emission leaves
        # the front as wound only)
        rows, p, nrm, back_off = shade_hits(
            dirs, hits, (float(st.max_distance), eps), sc.surface_tables, rd._double_sided,
            HitRecords(rec["kind"], t, rec["position"], rec["normal"], rec["albedo"],
                       rec["emission"]))
        sc._apply_textures(hits.prim_id, hits.u, hits.v, rec["albedo"], rec["emission"], rows)
        if sky_at_misses and not rd.environment.is_black:
            miss = np.flatnonzero(rec["kind"] == 0)
            if miss.size:
                rec["light_punctual"][miss] = rd._env.radiance(dirs[miss])
        if not rows.size:
            return rays
        which, s_org, s_dir, s_len, s_irr, ok = light_rays(p, nrm, rd._lights, eps,
                                                           self.tracer.centre)
        if len(which):
            occluded = self.tracer.occluded_rays(EmbreeRays(s_org, s_dir, s_len), ok)
            rays += len(which)
            scatter_divided(rec["light_punctual"], rows,
                            sum_unblocked(len(rows), which, occluded, s_irr), np.pi, False)
        # lit from a point offset short of the hit, back along the ray (shade_hits)
        if draw_e is not None:
            e_e, r = self.emitters.irradiance(back_off, nrm, draw_e(draw_rows[rows]),
                                              self.tracer, eps)
            rays += r
            scatter_divided(rec["light_emitters"], rows, e_e, np.pi, False)
        if draw_s is not None:  # the environment, sampled as a light (it no longer reaches the grid)
            e_s, r = self.sky.irradiance(back_off, nrm, draw_s(draw_rows[rows]), self.tracer,
                                         eps)
            rays += r
            scatter_divided(rec["light_emitters"], rows, e_s, np.pi, True)
        return rays

    def _shade_all(self, origins: NDArray[np.float64], dirs: NDArray[np.float64],
                   draw_rows: NDArray[np.int64], draw_e: Draw | None, draw_s: Draw | None, *,
                   sky_at_misses: bool
                   ) -> tuple[dict[str, NDArray[Any]], NDArray[np.float64], int]:
        """:meth:`_shade` of any number of rays, :data:`SHADE_CHUNK` at a time, into one set of
        records."""
        rec = _new_records(len(dirs))
        t = np.empty(len(dirs))
        rays = 0
        for c0 in range(0, len(dirs), SHADE_CHUNK):  # loop over chunks of rays, not rays
            sl = slice(c0, min(c0 + SHADE_CHUNK, len(dirs)))
            rays += self._shade(origins[sl], dirs[sl], draw_rows[sl], draw_e, draw_s,
                                {k: v[sl] for k, v in rec.items()}, t[sl],
                                sky_at_misses=sky_at_misses)
        return rec, t, rays

    def _gather_level(self, draw: Any, rays_per_probe: int, purposes: tuple[int, int, int],
                      rows: NDArray[np.int64], above: dict[str, NDArray[Any]],
                      arriving: NDArray[np.float64], parents: NDArray[np.int64], emitters: bool,
                      sky: bool) -> tuple[dict[str, NDArray[Any]], NDArray[np.float64], int]:
        """One gather level: a cosine-weighted ray from each hit ``parents`` of the level
        ``above`` (records with ``position`` and ``normal``, the normal facing the side the ray
        ``arriving`` came from), lit as a probe's rays are (one emitter and one environment
        sample; misses and emission count 0). Its random numbers are rows ``rows`` of the
        probes' streams of ``purposes`` (directions, emitters, environment; ``rays_per_probe``
        primary rays of K gather rays each per probe, :meth:`trace`'s ``draw``). Returns the
        records, the directions and the rays cast."""
        eps = self.settings.ray_offset
        kg = self.gather_samples
        per = rays_per_probe * kg
        org, dirs = gather_rays(above["position"], above["normal"], arriving, parents,
                                draw(purposes[0], per, 2, rows), eps)
        rec, _, rays = self._shade_all(org, dirs, rows,
                                       _light_draw(draw, purposes[1], per, int(emitters)),
                                       _light_draw(draw, purposes[2], per, int(sky)),
                                       sky_at_misses=False)
        return rec, dirs, rays

    def trace(self, positions: NDArray[np.float64], indices: NDArray[np.int64]
              ) -> tuple[dict[str, NDArray[Any]], NDArray[np.float32], int]:
        """Cast every ray of probes at ``positions (B, 3)`` (linear ``indices``) once.

        Returns the records, the probes' distance moments ``(B, 6, m, m, 2)`` and the rays cast.
        """
        st = self.settings
        rd = self.renderer
        n, s, m = st.face_size, st.samples, st.moments_size
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        b = len(pos)
        patterns = [sample_pattern(st, int(i)) for i in idx]
        dirs = np.stack([p[0].reshape(-1, 3) for p in patterns])
        wts = np.stack([p[1].reshape(-1) for p in patterns])
        nr = dirs.shape[1]
        flat = dirs.reshape(-1, 3)
        origins = np.repeat(pos, nr, axis=0)
        eps = st.ray_offset
        ls = self.light_samples if len(self.emitters) else 0
        ks = 0 if self.sky.is_black else self.light_samples
        kg = self.gather_samples

        keys: dict[int, NDArray[np.uint64]] = {}

        def draw(purpose: int, per: int, width: int, rows: NDArray[np.int64]
                 ) -> NDArray[np.float64]:
            # rows of the probes' streams of one purpose, ``per`` rows of ``width`` numbers per
            # probe: row r of the batch is row r % per of probe r // per. What a probe draws
            # depends only on its stream and the row, not on its batch or the other rows
            if purpose not in keys:
                keys[purpose] = _stream_keys(st.seed, idx, purpose)
            return stream_uniforms(keys[purpose], per, rows, width)

        rec, t, rays = self._shade_all(origins, flat, np.arange(b * nr),
                                       _light_draw(draw, 1, nr, ls), _light_draw(draw, 2, nr, ks),
                                       sky_at_misses=True)
        if kg:
            # final gather (module docstring): kg rays from every front hit, one more from each
            # of their hits at depth 2; a bounce reads the grid at the deepest level's hits
            front = np.flatnonzero(rec["kind"] == 1)
            rows = np.repeat(front, kg) * kg + np.tile(np.arange(kg), len(front))
            parent_row = np.repeat(front, kg)  # each ray's parent in the level above
            above, arriving = rec, flat
            for depth in range(1, self.gather_depth + 1):
                prefix = _LEVELS[depth]
                level, g_dir, cast = self._gather_level(
                    draw, nr, (3 * depth, 3 * depth + 1, 3 * depth + 2), rows, above, arriving,
                    parent_row, bool(ls), bool(ks))
                rays += cast
                for k in _gather_keys(deepest=depth == self.gather_depth):
                    rec[prefix + k] = level[k]
                rec[prefix + "primary"] = parent_row.astype(np.int32)
                hit = np.flatnonzero(level["kind"] == 1)  # the next level's parents, one ray each
                rows, parent_row = rows[hit], hit
                above, arriving = level, g_dir
        back = rec["kind"].reshape(b, nr) == 2
        moments = np.empty((b, 6, m, m, 2), dtype=np.float32)
        sa = rd._texel_sa * wts
        tt = t.reshape(b, nr)
        for j in range(b):  # per probe: the reductions must not depend on the batch
            moments[j] = distance_moments(tt[j], sa[j], rd._moment_bins,
                                          6 * m * m).reshape(6, m, m, 2)
        # the probe's direct view of the emitters (exact texel coverage) replaces what its
        # rays saw of their emission; the punctual lights it sees are folded in at the end
        view_tex, view_val, view_off = [], [], [0]
        for j in range(b):  # loop over probes, not rays
            tex, val, r = self.emitters.texel_view(pos[j], n, self.tracer, eps)
            rays += r
            em = rec["emission"][j * nr:(j + 1) * nr]
            seen = em if s == 1 else texel_means(em, wts[j], s)
            delta = -np.asarray(seen, np.float64)
            delta[tex] += val
            keep = np.flatnonzero(np.any(delta != 0, axis=1))
            view_tex.append(keep)
            view_val.append(delta[keep])
            view_off.append(view_off[-1] + len(keep))
        rec["view_texel"] = np.concatenate(view_tex).astype(np.int64)
        rec["view_value"] = np.concatenate(view_val).astype(np.float64).reshape(-1, 3)
        rec["view_offsets"] = np.array(view_off, np.int64)
        l_dir, l_e, l_off = [np.zeros((0, 3))], [np.zeros((0, 3))], [0]
        if st.direct and self.scene.lights:
            ldirs, e_perp, visible, r = rd._visible_lights(pos)
            rays += r
            for j in range(b):
                li = np.flatnonzero(visible[j])
                l_dir.append(ldirs[j, li])
                l_e.append(e_perp[j, li])
                l_off.append(l_off[-1] + len(li))
        else:
            l_off = [0] * (b + 1)
        rec["lights_direction"] = np.concatenate(l_dir)
        rec["lights_irradiance"] = np.concatenate(l_e)
        rec["lights_offsets"] = np.array(l_off, np.int64)
        rec["backface_fraction"] = back.mean(axis=1)
        rec["probes"] = idx
        rec["rays_per_probe"] = np.array(nr)
        rec["sky_sampled"] = np.array(bool(ks))
        return rec, moments, rays


@dataclass(frozen=True, eq=False)
class GridData:
    """What a pass reads of the whole grid: probe validity and positions, the distance moments
    (bordered, for the weights) and the previous level's irradiance cubes (bordered, flat
    ``(P * 6 (g + 2)^2, 3)``, or None for a black grid)."""

    grid: GridSpec
    valid: NDArray[np.bool_]
    positions: NDArray[np.float64]
    moments: NDArray[np.float32]
    moments_n: int
    cubes: NDArray[np.float32] | None


def grid_level_read(level: int, depth: int) -> int:
    """The grid level a pass at bounce ``level`` reads (negative: none) with ``depth`` gather
    levels: ``level - 1 - depth`` (each gather level's hits reflect light of the level below)."""
    return level - 1 - depth


def all_hit_weights(records: dict[str, NDArray[Any]], data: GridData
                    ) -> dict[str, NDArray[Any]]:
    """The probe weights of every hit a bounce reads the grid at: the deepest gather level's
    hits when the records have gather rays (the hits above read the light gathered below),
    else the rays' own hits. Returns the arrays to add to the records."""
    prefix = _LEVELS[gather_depth(records)]
    wi, ww = hit_weights({k: records[prefix + k] for k in ("kind", "position", "normal")}, data)
    return {prefix + "weight_index": wi, prefix + "weight": ww}


def weighted_positions(records: dict[str, NDArray[Any]]) -> tuple[str, ...]:
    """The positions no pass reads once :func:`all_hit_weights` are known: the deepest gather
    level's (the probes' own hits keep theirs: the final view weighs them again)."""
    depth = gather_depth(records)
    return (_LEVELS[depth] + "position",) if depth else ()


def has_hit_weights(records: dict[str, NDArray[Any]]) -> bool:
    """Whether :func:`all_hit_weights` was already added to ``records``."""
    return _LEVELS[gather_depth(records)] + "weight_index" in records


def hit_weights(records: dict[str, NDArray[Any]], data: GridData
                ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Each front hit's 8 probes and normalised DDGI weights (0 for misses and back hits)."""
    g = data.grid
    counts = np.array(g.counts, dtype=np.int64)
    bias = DEFAULT_NORMAL_BIAS * g.smallest_cell()
    return hit_probe_weights(
        np.ascontiguousarray(records["position"], dtype=np.float64),
        np.ascontiguousarray(records["normal"]), np.flatnonzero(records["kind"] == 1),
        GridLattice(g.lo, g.hi, np.where(counts > 1, g.spacing, 1.0), counts, CORNER_OFFSETS),
        ProbeTable(np.ascontiguousarray(data.valid, dtype=bool),
                   np.ascontiguousarray(data.positions, dtype=np.float64), data.moments,
                   data.moments_n),
        Weighting(bias, NORMAL_TERM_FLOOR, MIN_WEIGHT, CRUSH_THRESHOLD), CUBE_AXES)


#: Side, in texels, of the blocks of a probe's faces over which :func:`_smooth_gathered`
#: spreads the gather rays' noise.
GATHER_BLOCK = 8


def _smooth_gathered(records: dict[str, NDArray[Any]], settings: RenderSettings,
                     rad: NDArray[np.float32], gathered: NDArray[np.float32],
                     cubes: NDArray[np.float32], g: int,
                     sample_weights: NDArray[np.float64] | None) -> NDArray[np.float32]:
    """What a probe sees of its hits' gathered light, with the gather rays' noise spread over
    blocks of :data:`GATHER_BLOCK` texels: each front hit's ``albedo * gathered`` becomes
    ``albedo * G`` (the grid read at the hit itself: smooth, but biased) plus the block's
    solid-angle-weighted mean of ``albedo * (gathered - G)``. A block is the texels of an
    ``8 x 8`` square whose hits face one side (the normal's cube face): spread
    across the edge between a wall and the ceiling, the corrections moved light from the sample
    room's red wall to its ceiling (2-3 % of each against a path tracer). A block's integral is
    unchanged
    (so is every diffuse map and SH, up to rounding); within a block the gather's mean
    correction replaces its per-texel noise (two bakes of the sample room with other seeds:
    10 % per texel apart in level 0 without it). Needs the rays' own probe weights, and the
    rays' sample weights with several rays per texel."""
    n, s = settings.face_size, settings.samples
    nr = int(records["rays_per_probe"])
    kind = records["kind"]
    total = len(kind)
    zeros = np.zeros((total, 3), np.float32)
    _, at_hit = replay_radiance(  # albedo * G alone
        ReplayRecords(kind, zeros, zeros, zeros, records["albedo"], records["normal"],
                      records["weight_index"], records["weight"]),
        (cubes, g), CUBE_AXES, 1, np.zeros((0, 3), np.float32))
    front = kind == 1
    corr = np.where(front[:, None], records["albedo"].astype(np.float64) * gathered
                    - at_hit.astype(np.float64), 0.0)
    ray = np.arange(total)
    probe, local = np.divmod(ray, nr)
    texel = local // s
    face, rest = np.divmod(texel, n * n)
    row, col = np.divmod(rest, n)
    bs = min(GATHER_BLOCK, n)
    nb = -(-n // bs)
    # the side the hit faces (its normal's cube face): light is not moved across the edge
    # between a wall and the ceiling a block straddles
    side = direction_to_face(records["normal"])
    block = (((probe * 6 + face) * nb + row // bs) * nb + col // bs) * 6 + side
    w = texel_solid_angles(n).reshape(-1)[texel] * front
    if sample_weights is not None:
        w = w * sample_weights
    den = np.bincount(block, weights=w, minlength=int(block.max()) + 1)
    num = sum_rows(block, w[:, None] * corr, len(den))
    mean = np.divide(num, den[:, None], out=np.zeros_like(num), where=den[:, None] > 0)
    out = rad.astype(np.float64) - corr + np.where(front[:, None], mean[block], 0.0)
    return np.maximum(out, 0.0).astype(np.float32)


def _replay_level(records: dict[str, NDArray[Any]], prefix: str, level: int,
                  grid: NDArray[np.float32], gathered: NDArray[np.float32], g: int
                  ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """:func:`probegrid.bake.kernels.grid.replay_radiance` of one level's records (``prefix``,
    with its probe weights where it has them): the ``grid`` read at its hits, or the light
    ``gathered`` below them."""
    wi, ww = records.get(prefix + "weight_index"), records.get(prefix + "weight")
    if wi is None or ww is None:  # a level that reads no grid (the kernel reads no weights)
        if grid.shape[0]:  # (a bug, not bad input)
            raise RuntimeError(f"records {prefix or 'of the probes'} read the grid without "
                               "their probe weights")
        wi, ww = np.zeros((0, 8), np.int32), np.zeros((0, 8), np.float32)
    none = np.zeros((0, 3), np.float32)  # (a gather level keeps no emission, and normals
    return replay_radiance(  # only where its hits read the grid)
        ReplayRecords(records[prefix + "kind"], records.get(prefix + "emission", none),
                      records[prefix + "light_punctual"], records[prefix + "light_emitters"],
                      records[prefix + "albedo"], records.get(prefix + "normal", none), wi, ww),
        (grid, g), CUBE_AXES, level, gathered)


def replay(records: dict[str, NDArray[Any]], settings: RenderSettings, level: int,
           cubes: NDArray[np.float32] | None, *, final: bool
           ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A pass over a batch's records at bounce ``level`` with the bordered irradiance ``cubes``
    (None: a black grid) of the grid level the hits read: ``level - 1 - depth`` with ``depth``
    gather levels (:func:`grid_level_read`).

    Returns the probes' incoming cubes ``(B, 6, n, n, 3)`` float32 -- ``final``: what the probe
    sees (emission, its exact direct view of the emitters and the punctual lights included);
    otherwise the bounced light only -- and their texel radiances before the per-probe
    corrections (for the caller's bookkeeping).
    """
    n, s = settings.face_size, settings.samples
    probes = records["probes"]
    b = len(probes)
    empty = np.zeros((0, 3), np.float32)
    depth = gather_depth(records)
    g = irradiance_size(depth > 0)
    grid = empty if cubes is None else cubes

    # gather levels, deepest first: its hits read the grid; each level above reads the light
    # the level below brings back (the rays' hits reflect at level - 1, theirs at level - 2)
    below = empty
    for d in range(depth, 0, -1):
        parents = len(records[_LEVELS[d - 1] + "kind"])
        if level - d < 0:
            below = np.zeros((parents, 3), np.float32)
            continue
        _, reflected = _replay_level(records, _LEVELS[d], level - d,
                                     grid if d == depth else empty, below, g)
        below = mean_per_parent(records[_LEVELS[d] + "primary"], reflected, parents)
    rad, bnc = _replay_level(records, "", level, empty if depth else grid, below, g)
    wts = (np.stack([sample_pattern(settings, int(i))[1].reshape(-1) for i in probes])
           if s > 1 else None)
    if (final and depth and level >= 2 and grid.shape[0] and "weight_index" in records):
        rad = _smooth_gathered(records, settings, rad, below, grid, g,
                               None if wts is None else wts.reshape(-1))
    if not final and bool(records.get("sky_sampled", False)):
        # the environment reaches hits by sampling (light_emitters): the grid carries only
        # light reflected at least once, not what the probe's misses see of the sky
        bnc[records["kind"] == 0] = 0.0
    use = rad if final else bnc
    if wts is not None:
        cube = texel_means(use, wts.reshape(-1), s)
    else:
        cube = use
    cube = cube.reshape(b, 6, n, n, 3)
    if final:
        vo, lo = records["view_offsets"], records["lights_offsets"]
        for j in range(b):  # loop over probes: their sparse corrections
            flat = cube[j].reshape(-1, 3)
            tex = records["view_texel"][vo[j]:vo[j + 1]]
            if tex.size:
                flat[tex] = np.maximum(
                    flat[tex].astype(np.float64) + records["view_value"][vo[j]:vo[j + 1]], 0.0)
            if lo[j + 1] > lo[j]:
                cube[j] = splat_delta(cube[j], records["lights_direction"][lo[j]:lo[j + 1]],
                                      records["lights_irradiance"][lo[j]:lo[j + 1]])
    return cube, use
