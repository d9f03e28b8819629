#!/usr/bin/env bash
# The README's pictures, from the documented commands; run from the repository root.
set -euo pipefail
py=${PYTHON:-.venv/bin/python}
out=$(mktemp -d)
$py -m ti_dk.scene ellipse2d --out "$out" --no-snapshots
$py -m ti_dk.scene sphere3d --out "$out" --no-snapshots
$py -m ti_dk.scene ellipse2d --quick --movie --set movie_frames=12 --out "$out/quick" --no-snapshots
for fig in fig2 fig3 fig4; do $py -m studies.figures $fig --out "$out/figures"; done  # fig4: ~20 min
cp "$out/figures/fig2.png" renders/gallery/fig2_pdfs.png
cp "$out/figures/fig3.png" renders/gallery/fig3_equilibrium.png
cp "$out/figures/fig4.png" renders/gallery/fig4_void1d.png
$py - "$out" <<'PY'
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from PIL import Image

out, gallery = Path(sys.argv[1]), Path("renders/gallery")
third = lambda a: np.asarray(Image.fromarray(a).resize((a.shape[1] // 3, a.shape[0] // 3), Image.LANCZOS))  # noqa: E731
iio.imwrite(gallery / "ellipse2d_t00096.png", iio.imread(out / "ellipse2d_hybrid_frames/frame_0002.png"))
iio.imwrite(gallery / "sphere3d_t0015.png", iio.imread(out / "sphere3d_hybrid_frames/frame_0002.png"))
frames = [third(iio.imread(f)) for f in sorted((out / "quick/ellipse2d_hybrid_frames").glob("frame_*.png"))]
iio.imwrite(gallery / "ellipse2d_quick.gif", np.stack(frames), duration=150, loop=0)
PY
rm -rf "$out"
