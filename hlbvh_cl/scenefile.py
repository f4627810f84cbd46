"""``hlbvh_cl.scenefile``: TOML scene files and mesh files as scenes.  The
module lives in the scene I/O room (hlbvh_cl.io.scenefile); this name is
the one users import, kept as it was."""
import sys

from .io import scenefile as _room

sys.modules[__name__] = _room
