"""Running a scene: the step loop (:mod:`.controller`), its output handlers (:mod:`.handlers`), the
solver of a scene's method (:mod:`.registry`), checkpoints (:mod:`.checkpoint`), Taichi start-up,
stop signals and result types (:mod:`.runtime`), and ensembles on Dask workers (:mod:`.ensemble`)."""
