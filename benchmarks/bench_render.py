"""Seconds per frame (render + PNG) of the ellipse2d (256², two methods) and sphere3d (128³, two
methods) frames, on densities shaped like the scenes' (a void in a Poisson bulk, a region
around it). ``python benchmarks/bench_render.py [--frames 5]``; the first frame (matplotlib's font
cache, the volume kernel's compilation) is reported apart."""
import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import ti_dk
from ti_dk.output.render import FrameWriter, Panel, Renderer, colour_max


def density(n: int, dim: int, rng) -> tuple[np.ndarray, list]:
    x = (np.arange(n) + 0.5) / n - 0.5
    r2 = sum(a**2 for a in np.meshgrid(*([x] * dim), indexing="ij", sparse=True))
    ppc = rng.poisson(np.where(r2 < 0.3**2, 2.0, 30.0)).astype(float)
    lo, hi = int(0.18 * n), int(0.82 * n)
    step = max(2, (hi - lo) // 4)
    boxes = [(tuple(lo + step * np.array(c)), tuple(min(hi, lo + step * (c_ + 1)) for c_ in c))
             for c in np.ndindex(*([4] * dim))]
    return ppc, boxes


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=5)
    args = p.parse_args()
    ti_dk.init("cpu")
    rng = np.random.default_rng(1)
    for n, dim in ((256, 2), (128, 3)):
        ppc, boxes = density(n, dim, rng)
        r = Renderer((n,) * dim, (1.0,) * dim, 2, colour_max(np.array([30.0])), "bench")
        with tempfile.TemporaryDirectory() as d:
            w = FrameWriter(Path(d), r)
            times = []
            for k in range(args.frames + 1):
                t0 = time.perf_counter()
                w.write(0.001 * k, [Panel("hybrid", ppc, boxes), Panel("fv", ppc)])
                times.append(time.perf_counter() - t0)
        rest = np.array(times[1:])
        print(f"{n}^{dim}: first frame {times[0]:.2f} s, then {rest.mean():.3f} s per frame "
              f"(min {rest.min():.3f}, max {rest.max():.3f})")


if __name__ == "__main__":
    main()
