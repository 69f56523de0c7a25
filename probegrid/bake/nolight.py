"""No silent black: a bake with no light is refused, or says so.

Two checks and one rule:

* **Before any work** (:func:`require_light`): a scene with no emissive surface, no punctual
  light with a non-zero intensity and a black environment can only bake black; the ``probegrid
  bake`` job refuses it in one line unless asked for a black bake (``--allow-black``).
* **At the end of a bake** (:func:`light_quality`, called by the driver before the store is
  finished): when no *valid* probe received any light -- every probe inside geometry, or every
  light hidden from the probes -- the bake stops with the reason, and like every failed bake
  leaves no store and no work files (:func:`probegrid.bake.driver.bake`); the same command
  with ``--allow-black`` bakes the black store. A probe received light when its
  incoming cube's integral, ``2 sqrt(pi) L_00`` of its stored SH (all channels), is positive:
  the cube is non-negative, so a zero integral is an all-black cube.
* **Quality figures are never NaN**: a figure that has nothing to measure (the energy ratio of
  a bake whose probes all see black) reads ``"no light"``; the manifest says ``"light": "no
  light"`` or ``"lit"`` and how many valid probes were lit.
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.errors import ProbegridError
from probegrid.scene import Scene

__all__ = ["NO_LIGHT", "NoLightError", "emissive_materials", "light_quality", "light_sources",
           "printable", "require_light"]

#: What a quality figure reads when there is no light to measure it on.
NO_LIGHT: Final[str] = "no light"


class NoLightError(ProbegridError, ValueError):
    """A bake that can only be, or came out, black (one-line message)."""


def emissive_materials(scene: Scene) -> int:
    """Number of the materials the scene's triangles use that emit light."""
    used = np.unique(np.asarray(scene.material))
    emissive = 0
    for i in used:  # loop over materials, not triangles
        m = scene.materials[int(i)]
        tex = 1.0 if m.emissive_texture is None else float(np.max(m.emissive_texture))
        emissive += bool(np.max(m.emissive) * tex > 0)
    return emissive


def light_sources(scene: Scene, environment: Environment) -> list[str]:
    """The scene's sources of light, in words (empty: the bake can only be black)."""
    out = []
    emissive = emissive_materials(scene)
    if emissive:
        out.append(f"{emissive} emissive material{'s' if emissive > 1 else ''}")
    lights = sum(1 for li in scene.lights if li.intensity > 0 and max(li.color) > 0)
    if lights:
        out.append(f"{lights} punctual light{'s' if lights > 1 else ''}")
    env = environment
    if not env.is_black and (env.faces is None or float(np.max(env.faces)) > 0):
        out.append("the environment")
    return out


def require_light(scene: Scene, environment: Environment, *, allow_black: bool = False) -> None:
    """Refuse (:class:`NoLightError`) a scene and environment that hold no light at all."""
    if allow_black or light_sources(scene, environment):
        return
    raise NoLightError(
        "the scene has no light: no emissive material, no punctual light and no environment "
        "(give --environment or --environment-color, or --allow-black for a black bake)")


def light_quality(quality: dict[str, Any], sh: NDArray[Any], valid: NDArray[np.bool_], *,
                  allow_black: bool = True) -> dict[str, Any]:
    """``quality`` with the light figures added and no NaN left; raises :class:`NoLightError`
    when no valid probe received light, unless ``allow_black``.

    ``sh (P, 9, 3)``: the store's radiance SH (may be a memory map); ``valid (P,)``.
    """
    v = np.asarray(valid, dtype=bool)
    l00 = np.asarray(sh[:, 0, :], dtype=np.float64)  # (P, 3): integral / (2 sqrt(pi))
    lit = v & (l00.max(axis=1) > 0)
    n_valid, n_lit = int(v.sum()), int(lit.sum())
    if n_lit == 0 and not allow_black:
        reason = (f"every one of the {len(v)} probes is inside geometry" if n_valid == 0 else
                  f"none of the {n_valid} valid probes receives any light (every source is "
                  "hidden from them)")
        raise NoLightError(f"the bake came out black: {reason}; no store was written "
                           "(rerun with --allow-black to bake it black anyway)")
    out = {k: (NO_LIGHT if v_ is None or (isinstance(v_, float) and math.isnan(v_)) else v_)
           for k, v_ in quality.items()}
    out["light"] = "lit" if n_lit else NO_LIGHT
    out["lit_probes"] = n_lit
    return out


class _Printable:
    """A quality figure for a format string: numbers as asked, "no light" for the rest."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __format__(self, spec: str) -> str:
        v = self.value
        if v is None or isinstance(v, str) or (isinstance(v, float) and math.isnan(v)):
            return NO_LIGHT if v is None or not isinstance(v, str) else v
        return format(v, spec)


def printable(value: Any) -> Any:
    """``value`` wrapped so that ``f"{x:.2e}"`` prints "no light" for a missing figure."""
    return _Printable(value)
