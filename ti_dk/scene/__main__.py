"""``python -m ti_dk.scene``: the command line (:mod:`ti_dk.control.cli`). An entry point, the one kind
of module allowed to import from a layer above its own."""
import sys

from ..control.cli import main

sys.exit(main())
