"""The methods: the solver contract (:mod:`.solver`), finite-volume Dean–Kawasaki and its
Gaussian version (:mod:`.fv`, with its parts in :mod:`.fluxes` and :mod:`.passes`: paper eq.
7–11), independent Brownian particles (:mod:`.particles`); the registry that builds a scene's
solver is :mod:`ti_dk.control.registry`."""
