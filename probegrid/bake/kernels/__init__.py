"""Compiled per-ray kernels of the bake, by what they compute.

A bake handles every ray hit with the same short sequence of scalar steps: the hit's surface, its
shadow rays, the DDGI weights of the 8 probes around it (:mod:`probegrid.core.ddgi`, with a
seamless bilinear lookup of each probe's distance moments), and at every bounce the replay of
its record. Written as numpy array expressions these steps allocate a dozen ``(n, 8)`` and
``(n, 8, 3)`` temporaries per batch and cost many times the ray casting itself; here they are
one fused loop per hit, compiled by numba with the options and cache of :mod:`probegrid._jit`.
Kernels are pure functions of arrays (they allocate their outputs, or fill arrays passed for that
purpose) and release the GIL.

Each kernel restates, step for step, an array expression that stays the reference and the
documentation of the maths; ``tests/test_bake_kernels.py`` compares the two on random inputs.
The modules:

* :mod:`~probegrid.bake.kernels.cube` -- the cube map's conversions (a direction's face and
  ``(u, v)``, a probe's sample pattern) and the :class:`~probegrid.bake.kernels.cube.CubeAxes`
  table the other kernels read the faces' axes from;
* :mod:`~probegrid.bake.kernels.surfaces` -- the backface rule and the records pass at hits;
* :mod:`~probegrid.bake.kernels.lights` -- the punctual lights' shadow rays and the sums of
  unblocked shadow rays;
* :mod:`~probegrid.bake.kernels.grid` -- the trace-once probe weights, the replay of a bounce,
  per-texel means and distance moments;
* :mod:`~probegrid.bake.kernels.emitters` -- the emitters' exact polygon integrals, shadow rays,
  estimates and texel coverage;
* :mod:`~probegrid.bake.kernels.environment` -- the environment sampled as a light;
* :mod:`~probegrid.bake.kernels.sampling` -- alias tables, cosine-weighted directions, the final
  gather's rays, counter-based random streams;
* :mod:`~probegrid.bake.kernels.texels` -- the edge-aware smoothing of the gather's correction
  over a probe's texels.

Shadow rays are written as Embree takes them by the one rounding rule of
:func:`probegrid.raytrace.kernels._embree_ray` (:class:`probegrid.raytrace.EmbreeRays`): no
float64 copy of them is made and converted. A hit's vertex attributes are interpolated by
:func:`probegrid.scene.kernels._barycentric`.

Floating point: float64 throughout (float32 only where the data is, and the rays handed to
Embree), with FMA contraction and reciprocal multiplication allowed (:mod:`probegrid._jit`; nan
and inf keep their meaning). Two functions of the C library are replaced where they dominated a
kernel, each tested against numpy to the last bits: :func:`~probegrid.bake.kernels.emitters._angle`
(``atan2`` of the polygon integrals) and :func:`~probegrid.bake.kernels.sampling._turn` (``cos``
and ``sin`` of the gather's azimuths). Results match the references to a few ulps, and a bake's
float32 outputs come out bit-identical to the pure-numpy bake's in practice.

Conventions are the owning modules' and are passed in as tables, not restated: the cube faces'
axes (:data:`probegrid.core.cubemap.FACE_NORMALS`, ``FACE_U``, ``FACE_V``, as
:data:`~probegrid.bake.kernels.cube.CUBE_AXES`), the corner order
(:data:`probegrid.core.grid.CORNER_OFFSETS`) and the DDGI constants of :mod:`probegrid.core.ddgi`.
Numba would read module constants as compile-time constants, which may fold differently from the
same values passed at run time: a bake's outputs are kept bit for bit by passing them.
"""
