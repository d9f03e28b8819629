"""Running a scene: the step loop (:mod:`.controller`), its output handlers (:mod:`.handlers`),
checkpoints (:mod:`.checkpoint`), Taichi start-up, stop signals and result types (:mod:`.runtime`),
and ensembles on Dask workers (:mod:`.ensemble`)."""
