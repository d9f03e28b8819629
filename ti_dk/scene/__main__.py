"""``python -m ti_dk.scene``: the command line (:mod:`ti_dk.scene.cli`)."""
import sys

from .cli import main

sys.exit(main())
