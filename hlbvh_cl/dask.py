"""``hlbvh_cl.dask``: queries over dask arrays and frames over a cluster.
The module lives in the distribution room (hlbvh_cl.distributed.dask); this
name is the one users import, kept as it was."""
import sys

from .distributed import dask as _room

sys.modules[__name__] = _room
