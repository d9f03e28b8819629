#!/usr/bin/env bash
# The gallery's pictures (the README shows one; docs/studies.md lists them), from the commands docs/scenes.md shows; run from the repository root.
#   renders/gallery/make.sh [scenes|figures|all]     (default: all; figures take ~25 min, fig4 ~20 of them)
set -euo pipefail
py=${PYTHON:-.venv/bin/python}
what=${1:-all}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
gallery=renders/gallery
if [[ $what == scenes || $what == all ]]; then
    $py -m ti_dk.scene ellipse2d --out "$out"
    $py -m ti_dk.scene sphere3d --out "$out"  # 6 min on a quiet 2-core machine
    $py -m ti_dk.scene ellipse2d --quick --movie --set movie_frames=16 --out "$out/quick"
    $py -m ti_dk.scene void1d --method hybrid --ensemble 2000 --out "$out"
    $py -m ti_dk.scene trap1d --method particle --ensemble 300 --out "$out"
    $py -m ti_dk.scene doublewell2d --out "$out"
    cp "$out/ellipse2d_hybrid_frames/frame_0002.png" $gallery/ellipse2d_t00096.png
    cp "$out/sphere3d_hybrid_frames/frame_0002.png" $gallery/sphere3d_t0015.png
    cp "$out/quick/ellipse2d_quick_hybrid.mp4" $gallery/ellipse2d_quick.mp4
    cp "$out/void1d_hybrid_frames/frame_0001.png" $gallery/void1d_hybrid_t0025.png
    cp "$out/trap1d_particle_frames/frame_0000.png" $gallery/trap1d_particle.png
    cp "$out/doublewell2d_hybrid_frames/frame_0005.png" $gallery/doublewell2d_t005.png
fi
if [[ $what == figures || $what == all ]]; then
    for fig in fig2 fig3 fig4; do $py -m studies.figures $fig --out "$out/figures"; done
    cp "$out/figures/fig2.png" $gallery/fig2_pdfs.png
    cp "$out/figures/fig3.png" $gallery/fig3_equilibrium.png
    cp "$out/figures/fig4.png" $gallery/fig4_void1d.png
fi
