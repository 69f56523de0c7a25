"""probegrid: light-probe grids, cube-map environment filtering and a probe map service.

Conventions (face order, orientation, world frame, SH basis, units) are stated once in
:mod:`probegrid.conventions` and :mod:`probegrid.cubemap`.
"""

from probegrid.cubemap import CubeMap

__version__ = "0.1.0"
__all__ = ["CubeMap", "__version__"]
