"""``python -m hlbvh_cl``: the hlbvh-cl command (hlbvh_cl.cli)."""
import sys

from .cli import main

sys.exit(main())
