"""File formats that engines load as they are: KTX 2.0 textures (:mod:`probegrid.export.ktx2`),
probe grids packed the way three.js and Bevy sample them (:mod:`probegrid.export.engines`), and
filtered environments as Babylon.js (:mod:`probegrid.export.gltf_ibl`) and Filament
(:mod:`probegrid.export.filament`) load them.

Pure numpy (plus the optional ``zstandard`` package for supercompressed KTX2); no I/O beyond
writing and reading the files themselves.
"""
