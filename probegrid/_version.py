"""The package version (one place; :mod:`probegrid` re-exports it as ``probegrid.__version__``)."""

__version__ = "0.1.0"
