"""``python -m hlbvh_cl``: the hlbvh-cl command (hlbvh_cl.cli)."""
import sys

try:
    from .cli import main
except KeyboardInterrupt:  # Ctrl-C while the command's modules load: no traceback
    print("hlbvh-cl: interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
