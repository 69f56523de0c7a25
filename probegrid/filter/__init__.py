"""The environment filter: one HDR environment in; its diffuse map (irradiance / pi), GGX
specular mip chain, SH coefficients, DFG lookup table and quality figures out, as arrays.

* :mod:`probegrid.filter.settings`: :class:`FilterSettings`, every option with its default and
  bounds written once (``probegrid filter``'s options are generated from it), the checks of
  their combinations and the sizes chosen by default;
* :mod:`probegrid.filter.pipeline`: :func:`filter_environment`, the pipeline on arrays (no file
  I/O), and the :class:`FilteredEnvironment` it returns.

``probegrid filter`` (:mod:`probegrid.jobs.filter`) reads the input files, calls
:func:`filter_environment` and writes the maps, ``sh.json``, the LUT, the previews and the
manifest. The pipeline's modules load on the first call, so importing the settings stays light
(the command line builds its options from them for every command).
"""

from __future__ import annotations

from probegrid.filter.pipeline import (
    FilteredEnvironment,
    Progress,
    energy_ratio,
    filter_environment,
)
from probegrid.filter.settings import (
    DEFAULT_DIFFUSE_SOURCE,
    DEFAULT_MAX_SIZE,
    FilterSettings,
    check_settings,
    default_cube_size,
    diffuse_source_size,
)

__all__ = [
    "DEFAULT_DIFFUSE_SOURCE",
    "DEFAULT_MAX_SIZE",
    "FilterSettings",
    "FilteredEnvironment",
    "Progress",
    "check_settings",
    "default_cube_size",
    "diffuse_source_size",
    "energy_ratio",
    "filter_environment",
]
