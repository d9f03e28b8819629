"""Scenes: the schema with every key declared once (:mod:`.schema`), loading and validation
(:mod:`.load`, :mod:`.checks`), memory and work estimates (:mod:`.estimates`), initial conditions
(:mod:`.initial`), observables (:mod:`.observables`); ``python -m ti_dk.scene`` runs the command
line of :mod:`ti_dk.control.cli`."""
