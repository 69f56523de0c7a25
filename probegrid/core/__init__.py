"""Pure math, no I/O: cube-map geometry, sampling, SH, lobes, filters, layouts, shading, lights, grids.

Every function here works on numpy arrays and returns new arrays; nothing reads or writes a file,
opens a socket or reads settings. The modules, bottom up: ``arrays`` (shared helpers),
``cubemap`` (faces, texel directions,
solid angles), ``seams``, ``color``, ``lobes``, ``dfg``, ``sampling``, ``sh``, ``specular``,
``diffuse``, ``probefilter``, ``layouts``, ``shading``, ``lights``, ``grid``, ``ddgi`` (probe
weights and blending) and ``conventions`` (the record every file carries).
"""
