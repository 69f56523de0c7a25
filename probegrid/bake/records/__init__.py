"""Trace once, replay every bounce: per-hit records of a batch of probes.

A bake's bounces differ only in the light its grid carries, never in its rays. So each probe's
rays are cast once and what a bounce needs of each ray is kept as a record; a bounce is then a
pass over the records that reads only the grid's small per-probe data. The package, by stage:

* :mod:`~probegrid.bake.records.schema` -- the record format: a block's typed records (one
  level of rays after another) and their stored form, named arrays;
* :mod:`~probegrid.bake.records.tracer` -- :class:`RecordTracer`, the trace-once pass;
* :mod:`~probegrid.bake.records.replay` -- the hits' probe weights and the pass of a bounce;
* :mod:`~probegrid.bake.records.storage` -- where a block's records are kept between passes
  (files, memory, or both).

The bake's driver (:mod:`probegrid.bake.driver`) handles a block's records in their stored form
only, through the names below and :func:`probegrid.bake.records.replay.replay` (imported from its
module: the package's attribute ``replay`` is that module).
"""

from probegrid.bake.records.replay import (
    GridData,
    all_hit_weights,
    grid_level_read,
    hit_weights,
    irradiance_cubes,
    irradiance_size,
)
from probegrid.bake.records.schema import (
    gather_depth,
    has_hit_weights,
    record_bytes,
    select_probes,
    weighted_positions,
)
from probegrid.bake.records.storage import (
    RECORDS_MEMORY,
    load_records,
    records_file,
    remove_records,
    resolve_directory,
    save_records,
)
from probegrid.bake.records.tracer import RecordTracer

__all__ = [
    "RECORDS_MEMORY",
    "GridData",
    "RecordTracer",
    "all_hit_weights",
    "gather_depth",
    "grid_level_read",
    "has_hit_weights",
    "hit_weights",
    "irradiance_cubes",
    "irradiance_size",
    "load_records",
    "record_bytes",
    "records_file",
    "remove_records",
    "resolve_directory",
    "save_records",
    "select_probes",
    "weighted_positions",
]
