"""The one importer of numba: the compile options every kernel shares and the cache policy.

Kernels sit beside the code they speed up (:mod:`probegrid.raytrace.kernels`,
:mod:`probegrid.scene.kernels`, :mod:`probegrid.bake.kernels`) and are compiled by the
decorators here, so that one set of options makes every kernel's code:

* ``nogil``: a kernel releases the GIL (the executors' threads run kernels side by side);
* ``error_model="numpy"``: a division by zero gives inf or nan, as numpy's does, with no check;
* ``fastmath={"contract", "arcp"}``: FMA contraction and multiplication by a reciprocal are
  allowed, no other fast-math flag (nan and inf keep their meaning). A bake's outputs depend on
  these flags to the last bit: changing them changes the bake.

Cache policy: ``cache=True``. A kernel is compiled once per machine and signature into numba's
cache (``__pycache__`` beside its module, or ``NUMBA_CACHE_DIR``) and loaded from it by later
processes; numba invalidates an entry when its module's source changes.

One signature per kernel: numba compiles a kernel once per distinct argument type, and an
array's type includes whether it is writable. A memory-mapped record (read-only) and a freshly
computed one (writable) would compile the same kernel twice (each worker process of a machine's
first bake paying for it). The callers of a kernel pass its inputs through :func:`frozen`
(read-only, C-contiguous views: no copy of a contiguous array), so each kernel has one
signature per bake (``tests/test_jit.py`` checks a bake's cache).

Numba reads a kernel's global values (module constants, arrays) as compile-time constants,
which may fold differently from the same values passed as arguments; kernels therefore take
their tables (cube axes, grid lattice, weighting constants) as arguments, grouped in small named
tuples, which numba passes as plain structs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final, TypeVar

import numba
import numpy as np

__all__ = ["JIT_OPTIONS", "frozen", "inline_kernel", "kernel", "strict_kernel"]

F = TypeVar("F", bound=Callable[..., Any])

#: The compile options of every kernel of the bake, the tracer and the scene.
JIT_OPTIONS: Final[dict[str, Any]] = {
    "nogil": True, "cache": True, "error_model": "numpy", "fastmath": {"contract", "arcp"}}


def kernel(fn: F) -> F:
    """``fn`` compiled with :data:`JIT_OPTIONS` (a numba dispatcher)."""
    return numba.njit(**JIT_OPTIONS)(fn)  # type: ignore[no-any-return]


def inline_kernel(fn: F) -> F:
    """:func:`kernel`, inlined into the kernels that call it (numba's ``inline="always"``:
    for scalar steps called per ray, where a call passing several arrays costs more than the
    step)."""
    return numba.njit(inline="always", **JIT_OPTIONS)(fn)  # type: ignore[no-any-return]


def strict_kernel(fn: F) -> F:
    """``fn`` compiled with numba's defaults and the cache (no fast-math, Python's error
    model): for the integer and topology loops that need no float rules of their own
    (:mod:`probegrid.bake.inside`)."""
    return numba.njit(cache=True)(fn)  # type: ignore[no-any-return]


V = TypeVar("V")


def frozen(value: V) -> V:
    """``value`` as a kernel reads it: an array as a read-only C-contiguous view (a copy only
    when it is not contiguous; the same values either way), a tuple (named or not) with each
    member frozen, anything else unchanged. The one argument type of a kernel's inputs, whether
    the caller's arrays are writable or memory-mapped read-only (module docstring)."""
    if isinstance(value, np.ndarray):
        view = (value if value.flags.c_contiguous else np.ascontiguousarray(value)).view()
        view.flags.writeable = False
        return view  # type: ignore[return-value]
    if isinstance(value, tuple):
        members = [frozen(v) for v in value]
        if hasattr(value, "_fields"):  # a named tuple
            return type(value)(*members)  # type: ignore[return-value]
        return tuple(members)  # type: ignore[return-value]
    return value
