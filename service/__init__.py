"""The probegrid map service: FastAPI app serving probe grids at any position.

Build it with :func:`service.main.create_app` (stores + :class:`service.settings.Settings`) and run
it with :func:`service.main.run` (``probegrid serve``). Routes, formats, errors and limits are
described in :mod:`service.main`, :mod:`service.encoding`, :mod:`service.errors` and
:mod:`service.settings`.
"""

from service.main import create_app, run
from service.settings import Settings

__all__ = ["Settings", "create_app", "run"]
