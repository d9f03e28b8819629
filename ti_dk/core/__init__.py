"""Numerics every method shares: the grid and its boundaries, counter-based random numbers,
streaming moments, and the exact answers the tests and figures compare with."""
