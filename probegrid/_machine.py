"""What this process may use of the machine: its cores.

The number of cores is the process's CPU affinity (what ``taskset``, a container's cpuset or a
batch scheduler grants it), not the machine's total: threads beyond it only queue. Library
functions that split work between threads take a ``workers`` argument and default to
:func:`available_cores`.
"""

from __future__ import annotations

import os

__all__ = ["available_cores"]


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; the machine's count where the system
    has no affinity call), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)
