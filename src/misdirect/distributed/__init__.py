"""Past one machine: the sweep, and the Dask side of :class:`misdirect.solvers.pool.TaskPool`.

Optional: ``pip install 'misdirect[cluster]'`` brings Dask distributed and pyarrow. Importing
this package imports neither; :func:`connect` does, when a cluster is asked for.
"""

from misdirect.distributed.pool import DaskPool, connect, where_am_i
from misdirect.distributed.sweep import SweepReport, SweepSpec, load_sweep, run_sweep

__all__ = [
    "DaskPool",
    "SweepReport",
    "SweepSpec",
    "connect",
    "load_sweep",
    "run_sweep",
    "where_am_i",
]
