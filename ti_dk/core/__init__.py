"""What every layer shares: the grid and its boundaries, counter-based random numbers, streaming
moments, the formulas and the external potential that kernels compile (:mod:`.expr`), the errors
(:mod:`.errors`), and the exact answers the tests and figures compare with."""
