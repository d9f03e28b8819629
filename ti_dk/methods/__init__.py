"""The methods: the solver contract (:mod:`.solver`), finite-volume Dean–Kawasaki and its
Gaussian version (:mod:`.fv`, :mod:`.fluxes`: paper eq. 7–11), independent Brownian particles
(:mod:`.particles`), and the registry that builds a scene's solver (:mod:`.registry`)."""
