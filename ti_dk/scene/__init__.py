"""Scenes: the schema with every key declared once (:mod:`.schema`), loading and validation
(:mod:`.load`), memory and work estimates (:mod:`.estimates`), initial conditions
(:mod:`.initial`), and the command line ``python -m ti_dk.scene`` (:mod:`.cli`)."""
