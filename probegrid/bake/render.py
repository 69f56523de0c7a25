"""Rendering the IncomingLight cube of a scene at probe positions, by ray casting through Embree.

For each probe, one ray per texel sample leaves the probe position; the texel holds the mean
radiance its rays bring back (:class:`RenderSettings.samples` rays per texel, jittered inside
the texel by a seeded, deterministic pattern and weighted by the cube's area element
``(1 + u^2 + v^2)^(-3/2)``, so the texel value estimates the mean radiance over its solid angle).

What a ray brings back
----------------------
* A miss: the environment (:mod:`probegrid.bake.environment`), box-filtered to the texel's footprint
  (:attr:`RenderSettings.environment_footprint`), so a sun smaller than a texel keeps its energy.
* A hit on the front of a surface (the geometric normal faces the ray; double-sided materials
  have no back): the outgoing radiance of a Lambertian surface,

      L = emission + albedo / pi * (E_direct(x, n) + E_indirect(x, n))

  with ``E_direct`` the irradiance of the punctual lights (:mod:`probegrid.core.lights`: candela,
  lux and the glTF range window), each checked with a shadow ray, and ``E_indirect`` the
  irradiance of the *previous bounce's* probe grid at the hit, interpolated with the
  leak-free weights of :func:`probegrid.core.ddgi.probe_weights` (normal-facing term and
  Chebyshev visibility from the distance moments) and evaluated from each probe's 9 SH
  coefficients at the normal (Ramamoorthi & Hanrahan 2001). Bounce 0 has no indirect term, so
  after ``k`` bounces a closed furnace box of albedo rho and emission Le reads
  ``Le (1 - rho^(k+1)) / (1 - rho)``.
* A hit on the back of a single-sided surface: black, and counted. A probe most of whose rays
  hit backfaces is inside geometry (:func:`backface_fraction`).

Punctual lights are deltas no ray can hit. Unless ``direct=False``, each probe receives the
direct light of every light it sees (a shadow ray from the probe) folded into its incoming cube
by :func:`probegrid.core.lights.splat_delta`, which spreads it over the texels around the light's
direction so the cube's solid-angle integral carries exactly the irradiance ``I / d^2`` (with the
spec's falloff); every filter then sees it. ``direct=False`` leaves it out, for engines that
light directly at run time.

Visibility moments
------------------
Every probe also records, per texel of a small ``moments_size`` cube, the solid-angle-weighted
mean distance and mean squared distance to the first hit of its rays (misses count as
``max_distance``), the inputs of DDGI's Chebyshev test (Majercik et al. 2019).

Determinism
-----------
A probe's jitter comes from :func:`probegrid.bake.executors.probe_rng` (its seed and linear index),
rays are traced independently and every reduction is done per probe, so a probe's result does
not depend on which batch or process rendered it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.executors import probe_rng
from probegrid.core import sh
from probegrid.core.cubemap import (
    FACE_NORMALS,
    FACE_U,
    FACE_V,
    texel_directions,
    texel_solid_angles,
)
from probegrid.core.ddgi import (
    CRUSH_THRESHOLD,
    DEFAULT_NORMAL_BIAS,
    MIN_WEIGHT,
    NORMAL_TERM_FLOOR,
    BorderedCubes,
    probe_weights,
)
from probegrid.core.grid import CORNER_OFFSETS, GridSpec
from probegrid.core.lights import incident_many, pack_lights, splat_delta
from probegrid.kernels import (
    cube_sample_directions,
    distance_moments,
    indirect_irradiance,
    light_rays,
    orient_hits,
    outgoing_radiance,
    texel_means,
)
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = [
    "IndirectField",
    "ProbeRenderer",
    "RenderResult",
    "RenderSettings",
    "probe_irradiance_coefficients",
    "sample_pattern",
]

# R2 low-discrepancy sequence (Roberts 2018): the plastic number's inverse powers.
_PLASTIC = 1.32471795724474602596
_R2 = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])


#: Rays shaded together: every per-ray temporary of a chunk stays in cache-sized, reused memory
#: (a whole batch of probes at once spends much of its time in page faults). Each ray's result
#: does not depend on its chunk.
SHADE_CHUNK = 1 << 15


@dataclass(frozen=True)
class RenderSettings:
    """How a probe's incoming cube is rendered.

    Attributes
    ----------
    face_size : int
        Face size of the incoming cube.
    samples : int
        Rays per texel. 1 shoots through the texel centre; more are an R2 low-discrepancy
        pattern with a per-probe random shift (Cranley-Patterson rotation).
    seed : int
        Bake seed; a probe's randomness depends on it and the probe's index only.
    moments_size : int
        Face size of the visibility-moments cube.
    direct : bool
        Fold the punctual lights' direct light into the probe's cube.
    ray_offset : float
        Distance rays start off a surface (shadow rays, metres).
    max_distance : float
        Distance recorded for misses in the moments.
    """

    face_size: int = 32
    samples: int = 1
    seed: int = 0
    moments_size: int = 8
    direct: bool = True
    ray_offset: float = 1e-4
    max_distance: float = 1e3

    @property
    def environment_footprint(self) -> int:
        """Face size of the environment cube misses read (box-filtered to it,
        :meth:`probegrid.bake.environment.Environment.sampler`): the incoming cube's, whatever the
        samples per texel. A texel holds the mean radiance over its solid angle, and each of its
        rays then reads the environment's mean over a texel-sized footprint, so the texel mean
        keeps the environment's energy (measured on venice_sunset at 32^2: sunward irradiance
        exact, worst texel 1.1 %; a finer footprint of 64^2 with 4 samples: 3.3 %); more samples
        still resolve the edges of geometry inside the texel."""
        return self.face_size

    def __post_init__(self) -> None:
        for name in ("face_size", "samples", "moments_size"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.face_size % self.moments_size:
            raise ValueError(
                f"moments_size {self.moments_size} must divide face_size {self.face_size}"
            )
        if not (self.ray_offset > 0 and np.isfinite(self.ray_offset)):
            raise ValueError(f"ray_offset must be > 0, got {self.ray_offset}")
        if not (self.max_distance > 0 and np.isfinite(self.max_distance)):
            raise ValueError(f"max_distance must be > 0, got {self.max_distance}")


def sample_pattern(settings: RenderSettings, probe_index: int) -> tuple[
    NDArray[np.float64], NDArray[np.float64]
]:
    """Ray directions of one probe and their weights within their texels.

    Returns
    -------
    directions : (6, n, n, s, 3) float64
        Unit directions, ``s = settings.samples`` per texel.
    weights : (6, n, n, s) float64
        Area-element weights normalised to sum to 1 over each texel's samples.
    """
    if settings.samples == 1:  # texel centres: the same for every probe
        return _centre_pattern(settings.face_size)
    return _sample_pattern(settings, probe_index)


@lru_cache(maxsize=8)
def _centre_pattern(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    d, w = _sample_pattern(RenderSettings(face_size=n, moments_size=1), 0)
    d.setflags(write=False)
    w.setflags(write=False)
    return d, w


def _jitter(settings: RenderSettings, probe_index: int) -> NDArray[np.float64]:
    """``(s, 2)`` positions of a probe's samples inside every texel, in ``[0, 1)^2``: the
    centre for one sample, else the R2 sequence shifted by the probe's random offset."""
    s = settings.samples
    if s == 1:
        return np.array([[0.5, 0.5]])
    shift = probe_rng(settings.seed, probe_index).random(2)
    return np.mod(0.5 + np.arange(1, s + 1)[:, None] * _R2[None, :] + shift, 1.0)


def _sample_pattern(settings: RenderSettings, probe_index: int) -> tuple[
    NDArray[np.float64], NDArray[np.float64]
]:
    n = settings.face_size
    jitter = _jitter(settings, probe_index)
    # sample k of texel (row, col) at continuous texel coordinates (col - 0.5 + jitter_x,
    # row - 0.5 + jitter_y), weighted by the area element (1 + u^2 + v^2)^(-3/2)
    return cube_sample_directions(n, np.ascontiguousarray(jitter, dtype=np.float64),
                                  FACE_NORMALS, FACE_U, FACE_V)


def probe_irradiance_coefficients(
    sh_l: NDArray[np.float64], *, out: NDArray[np.float64] | None = None, chunk: int = 1 << 16
) -> NDArray[np.float64]:
    """Irradiance coefficients ``A_l L_lm`` of radiance coefficients ``(P, 9, 3)``, ``chunk``
    probes at a time (into ``out`` when given); ``(P, 9, 3)`` float64."""
    if out is None:
        out = np.empty(sh_l.shape, dtype=np.float64)
    for s in range(0, len(sh_l), chunk):  # loop over chunks of probes: bounded temporaries
        part = np.asarray(sh_l[s:s + chunk], dtype=np.float64)
        out[s:s + len(part)] = np.moveaxis(
            sh.irradiance_coefficients(np.moveaxis(part, 1, 0)), 0, 1)
    return out


@dataclass(frozen=True, eq=False)
class IndirectField:
    """Irradiance of the previous bounce's probe grid at surface points.

    Attributes
    ----------
    grid : GridSpec
    sh : (P, 9, 3) float64
        Radiance SH coefficients of every probe.
    valid : (P,) bool
    positions : (P, 3) float64
        Probe positions (possibly moved).
    moments : (P, 6, m, m, 2) float32, BorderedCubes or None
        Distance moments for the Chebyshev visibility test (or their bordered form).
    coeffs : (P, 9, 3) float64, optional
        Irradiance coefficients ``A_l L_lm`` of ``sh`` when already computed.

    Any of the arrays may be read-only memory maps: a worker then reads the pages of the probes
    its rays reach, and its memory does not grow with the grid.
    """

    grid: GridSpec
    sh: NDArray[np.float64]
    valid: NDArray[np.bool_]
    positions: NDArray[np.float64]
    moments: NDArray[np.float32] | BorderedCubes | None = None
    coeffs: NDArray[np.float64] | None = None

    @cached_property
    def _irradiance_coeffs(self) -> NDArray[np.float64]:
        # (P, 9, 3) irradiance coefficients A_l L_lm
        if self.coeffs is not None:
            return self.coeffs
        return probe_irradiance_coefficients(self.sh)

    @cached_property
    def _moments(self) -> BorderedCubes | None:
        if self.moments is None or isinstance(self.moments, BorderedCubes):
            return self.moments
        return BorderedCubes(self.moments)

    @cached_property
    def _kernel_args(self) -> tuple:
        g = self.grid
        counts = np.array(g.counts, dtype=np.int64)
        cells = g.cell_size[counts > 1]
        bias = DEFAULT_NORMAL_BIAS * (float(cells.min()) if cells.size else 0.0)
        mom = self._moments
        data = np.zeros((0, 2), np.float32) if mom is None else mom.data
        m = 1 if mom is None else mom.n
        return (g.lo, g.hi, np.where(counts > 1, g.spacing, 1.0), counts, CORNER_OFFSETS,
                np.ascontiguousarray(self.valid, dtype=bool),
                np.ascontiguousarray(self.positions, dtype=np.float64), data, m, bias,
                np.ascontiguousarray(self._irradiance_coeffs), sh.BASIS_SCALE, FACE_U, FACE_V,
                NORMAL_TERM_FLOOR, MIN_WEIGHT, CRUSH_THRESHOLD)

    def irradiance(self, points: NDArray[np.float64], normals: NDArray[np.float64]
                   ) -> NDArray[np.float64]:
        """Irradiance (lux, RGB) at ``points (n, 3)`` with unit ``normals (n, 3)``; ``(n, 3)``.

        The compiled :func:`probegrid.kernels.indirect_irradiance`; :meth:`irradiance_reference`
        is the same computation in numpy array expressions (tests compare them).
        """
        if len(points) == 0:
            return np.zeros((0, 3))
        return indirect_irradiance(np.ascontiguousarray(points, dtype=np.float64),
                                   np.ascontiguousarray(normals, dtype=np.float64),
                                   *self._kernel_args)

    def irradiance_reference(self, points: NDArray[np.float64], normals: NDArray[np.float64]
                             ) -> NDArray[np.float64]:
        """:meth:`irradiance` through :func:`probegrid.core.ddgi.probe_weights` and the SH
        basis: the readable statement of what the kernel computes."""
        if len(points) == 0:
            return np.zeros((0, 3))
        pw = probe_weights(
            self.grid, points, valid=self.valid, normals=normals,
            probe_positions=self.positions, moments=self._moments,
        )
        basis = sh.sh_basis(normals)  # (n, 9)
        coeffs = self._irradiance_coeffs
        e = np.zeros((len(points), 3))
        for c in range(8):  # corner by corner: (n, 9, 3) gathers instead of one (n, 8, 9, 3)
            e += pw.weights[:, c, None] * np.einsum("nk,nkj->nj", basis, coeffs[pw.indices[:, c]])
        return np.maximum(e, 0.0)


@dataclass
class RenderResult:
    """A batch of rendered probes.

    Attributes
    ----------
    incoming : (B, 6, n, n, 3) float32
        Incoming radiance cubes (with the direct light folded in unless disabled).
    moments : (B, 6, m, m, 2) float32
        Mean distance and mean squared distance per moments texel.
    backface_fraction : (B,) float64
        Fraction of primary rays that hit the back of a single-sided surface.
    rays : int
        Rays cast (primary and shadow).
    """

    incoming: NDArray[np.float32]
    moments: NDArray[np.float32]
    backface_fraction: NDArray[np.float64]
    rays: int


class ProbeRenderer:
    """Renders incoming cubes of one scene (build once per process: it owns the BVH)."""

    def __init__(
        self,
        scene: Scene,
        environment: Environment | None = None,
        settings: RenderSettings | None = None,
        *,
        tracer: RayTracer | None = None,
    ) -> None:
        self.scene = scene
        self.environment = environment or Environment()
        self.settings = settings or RenderSettings()
        self.tracer = tracer or RayTracer.from_scene(scene)
        self._env = self.environment.sampler(self.settings.environment_footprint)
        self._double_sided = scene.double_sided
        n, m = self.settings.face_size, self.settings.moments_size
        f, r, c = np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij")
        k = n // m
        bins = (f * m + r // k) * m + c // k  # moments texel of every incoming texel
        self._moment_bins = np.repeat(bins.reshape(-1), self.settings.samples)
        self._texel_sa = np.repeat(texel_solid_angles(n).reshape(-1), self.settings.samples)

    # -- shading -------------------------------------------------------------------------

    def _visible_lights(
        self, points: NDArray[np.float64], normals: NDArray[np.float64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], int]:
        """Which punctual lights reach which points, by shadow rays.

        One shadow ray per (point, light) pair that could deliver light (``E_perp > 0`` and, when
        ``normals (p, 3)`` are given, the light in front of the surface), starting
        ``ray_offset`` off the point (along the normal when given).

        Returns
        -------
        directions (p, L, 3), e_perp (p, L, 3), visible (p, L) bool, rays cast
        """
        dirs, e_perp, dist = incident_many(self.scene.lights, points)
        lit = e_perp.max(axis=-1) > 0
        if normals is not None:
            lit &= np.einsum("pli,pi->pl", dirs, normals) > 0
        pi, li = np.nonzero(lit)
        eps = self.settings.ray_offset
        origins = points[pi] if normals is None else points[pi] + eps * normals[pi]
        tmax = np.where(np.isfinite(dist[pi, li]), dist[pi, li] - eps, np.inf)
        visible = np.zeros(lit.shape, dtype=bool)
        if pi.size:
            visible[pi, li] = ~self.tracer.occluded(origins, dirs[pi, li], tmax, tmin=eps)
        return dirs, e_perp, visible, len(pi)

    @cached_property
    def _lights(self) -> tuple:
        pk = pack_lights(self.scene.lights)
        return (pk.kind.astype(np.int64), pk.position, pk.axis, pk.power, pk.range,
                pk.angle_scale, pk.angle_offset)

    def _shade(self, origins: NDArray[np.float64], dirs: NDArray[np.float64],
               field: IndirectField | None) -> tuple[NDArray[np.float32], NDArray[np.float64],
                                                     NDArray[np.bool_], int]:
        """Radiance, hit distance and backface flag of rays ``(N, 3)`` from ``origins (N, 3)``.

        Misses read the environment; front hits get ``emission + albedo / pi * E`` with ``E``
        the unshadowed punctual lights (one shadow ray per light in front of the surface,
        :func:`probegrid.kernels.light_rays`) plus the previous bounce's grid
        (:meth:`IndirectField.irradiance`); back hits are black.
        """
        hits = self.tracer.intersect(origins, dirs)
        radiance = np.zeros((len(dirs), 3), dtype=np.float32)
        miss = hits.prim_id < 0
        if miss.any() and not self.environment.is_black:
            radiance[miss] = self._env.radiance(dirs[miss])
        hit = np.flatnonzero(~miss)
        back = np.zeros(len(dirs), dtype=bool)
        rays = len(dirs)
        if hit.size:
            prim = hits.prim_id[hit]
            pos, nrm, albedo, emission = self.scene.surface_at(prim, hits.u[hit], hits.v[hit])
            is_back = orient_hits(nrm, dirs, hit, prim, self._double_sided)
            back[hit] = is_back
            fh = np.flatnonzero(~is_back)
            if fh.size < hit.size:
                pos, nrm = pos[fh], nrm[fh]
                albedo, emission = albedo[fh], emission[fh]
            e = np.zeros((len(fh), 3)) if field is None else field.irradiance(pos, nrm)
            eps = self.settings.ray_offset
            which, s_org, s_dir, s_tmax, s_irr = light_rays(pos, nrm, *self._lights, eps)
            occluded = (self.tracer.occluded(s_org, s_dir, s_tmax, tmin=eps) if len(which)
                        else np.zeros(0, dtype=bool))
            rays += len(which)
            radiance[hit[fh]] = outgoing_radiance(emission, albedo, e, which, s_irr, occluded)
        t = np.where(miss, self.settings.max_distance,
                     np.minimum(hits.t, self.settings.max_distance))
        return radiance, t, back, rays

    # -- probes --------------------------------------------------------------------------

    def render(
        self,
        positions: NDArray[np.float64],
        indices: NDArray[np.int64],
        *,
        field: IndirectField | None = None,
        direct: bool | None = None,
    ) -> RenderResult:
        """Render the incoming cubes of probes at ``positions (B, 3)`` with linear ``indices``.

        ``direct`` overrides :attr:`RenderSettings.direct` (folding the punctual lights' direct
        light into the cubes). A bake's intermediate bounces render without it: their grids are
        the indirect light at later bounces' surface points, which get the lights' direct
        light from their own shadow rays (through the grid it would be counted twice).
        """
        st = self.settings
        n, s, m = st.face_size, st.samples, st.moments_size
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        b = len(pos)
        patterns = [sample_pattern(st, int(i)) for i in idx]
        dirs = np.stack([p[0].reshape(-1, 3) for p in patterns])  # (B, R, 3)
        wts = np.stack([p[1].reshape(-1) for p in patterns])  # (B, R)
        nr = dirs.shape[1]
        origins = np.repeat(pos, nr, axis=0)
        flat = dirs.reshape(-1, 3)
        radiance = np.empty((len(flat), 3), dtype=np.float32)
        t = np.empty(len(flat))
        back = np.empty(len(flat), dtype=bool)
        rays = 0
        for c in range(0, len(flat), SHADE_CHUNK):  # loop over chunks of rays, not rays
            sl = slice(c, c + SHADE_CHUNK)
            radiance[sl], t[sl], back[sl], r = self._shade(origins[sl], flat[sl], field)
            rays += r
        if s == 1:  # one ray per texel: its weight is exactly 1
            incoming = radiance.reshape(b, 6, n, n, 3)
        else:
            incoming = texel_means(radiance, wts.reshape(-1), s).reshape(b, 6, n, n, 3)
        t = t.reshape(b, nr)
        backfrac = back.reshape(b, nr).mean(axis=1)

        moments = np.empty((b, 6, m, m, 2), dtype=np.float32)
        sa = self._texel_sa * wts.reshape(b, nr)  # solid angle carried by each ray
        for j in range(b):  # per probe: the reductions must not depend on the batch
            moments[j] = distance_moments(t[j], sa[j], self._moment_bins,
                                          6 * m * m).reshape(6, m, m, 2)

        if (st.direct if direct is None else direct) and self.scene.lights:
            rays += self._splat_direct(pos, incoming)
        return RenderResult(incoming, moments, backfrac, rays)

    def _splat_direct(self, pos: NDArray[np.float64], incoming: NDArray[np.float32]) -> int:
        """Fold each visible punctual light into the probes' cubes (in place); returns rays."""
        dirs, e_perp, visible, rays = self._visible_lights(pos)
        for j in np.flatnonzero(visible.any(axis=1)):  # loop over probes, not rays
            li = np.flatnonzero(visible[j])
            incoming[j] = splat_delta(incoming[j], dirs[j, li], e_perp[j, li])
        return rays

    def backface_fraction(self, positions: NDArray[np.float64], *, face_size: int = 8
                          ) -> NDArray[np.float64]:
        """Fraction of ``6 face_size^2`` texel-centre rays from each point that hit a backface.

        A cheap test for probes inside geometry; ``positions (B, 3)``, returns ``(B,)``.
        Double-sided materials have no back.
        """
        return self.surroundings(positions, face_size=face_size)[0]

    def surroundings(self, positions: NDArray[np.float64], *, face_size: int = 8
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """What ``6 face_size^2`` texel-centre rays from each point find: the fraction that hit a
        backface (:meth:`backface_fraction`) and the distance of the farthest hit (inf when a
        ray misses), which tells a point enclosed by a small closed surface -- inside a
        double-sided solid, whose inside shows no backface -- from one in open space.

        ``positions (B, 3)``; returns two ``(B,)`` float64 arrays.
        """
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        d = texel_directions(face_size).reshape(-1, 3)
        dirs = np.tile(d, (len(pos), 1))
        hits = self.tracer.intersect(np.repeat(pos, len(d), axis=0), dirs)
        prim = hits.prim_id
        back = self.tracer.backface(prim, dirs) & ~self._double_sided[np.maximum(prim, 0)]
        farthest = np.where(prim < 0, np.inf, hits.t).reshape(len(pos), -1).max(axis=1)
        return back.reshape(len(pos), -1).mean(axis=1), farthest
