"""Running a scene: the command line (:mod:`.cli`), the run options (:mod:`.options`), the step loop
(:mod:`.controller`), its output handlers (:mod:`.handlers`), the solver of a scene's method
(:mod:`.registry`), checkpoints (:mod:`.checkpoint`), Taichi start-up and result types
(:mod:`.runtime`), stop signals (:mod:`.signals`), ensembles on Dask workers (:mod:`.ensemble`) and
the speed/accuracy pilot (:mod:`.tradeoff`)."""
