"""The command-line jobs: options -> settings -> library calls -> output folders.

``bake`` (scene, grid, environment, executor -> :func:`probegrid.bake.bake`), ``filter`` (one HDR
environment -> diffuse, specular, SH, DFG, previews), ``export`` (a store's probes and facts),
``samples`` (the bundled sample room and sky) and ``demo`` (all of them on the sample data).
"""
