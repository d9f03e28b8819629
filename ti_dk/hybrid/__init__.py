"""The AMAR hybrid (paper §3): the solver and its step order (:mod:`.solver`), the walk, entry cap
and S1/S2 synchronisation of eq. 12 (:mod:`.sync`), regrids and extensions (:mod:`.regridder`), the particle region
(:mod:`.region`), particles sampled from the SPDE (:mod:`.ghosts`) and Berger–Rigoutsos clustering
(:mod:`.clustering`)."""
