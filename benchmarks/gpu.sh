#!/usr/bin/env bash
# Issue 13's benchmarks and the two big scenes on the CUDA backend, written to one Markdown file.
#
#     bash benchmarks/gpu.sh [OUT.md]        (default: benchmarks/gpu_results.md)
#
# Needs a CUDA driver (ti_dk refuses --arch cuda without one). Each part's wall time includes
# start-up and JIT; the tables inside come from the benchmark scripts themselves (bench_speed.py
# reports the best of 3 blocks after a warm-up step). The NumPy row of bench_speed.py runs on the
# CPU in any case; its "threads" column means nothing on CUDA.
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
PY=${PYTHON:-python}
OUT=${1:-benchmarks/gpu_results.md}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

{
  echo "# ti_dk on CUDA ($(date -u +%Y-%m-%d), $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $(git rev-parse --short HEAD 2>/dev/null))"
  echo
  echo "## bench_speed.py --arch cuda"
  echo
  $PY benchmarks/bench_speed.py --arch cuda --threads 1 2>&1 | grep -v '^\[Taichi\]'
  echo
  echo "## bench_fv.py --arch cuda"
  echo
  $PY benchmarks/bench_fv.py --arch cuda 2>&1 | grep -v '^\[Taichi\]'
  echo
  echo "## bench_hybrid.py --arch cuda"
  echo
  $PY benchmarks/bench_hybrid.py --arch cuda 2>&1 | grep -v '^\[Taichi\]'
  echo
  echo "## hybrid_value.py --arch cuda (issue 26: hybrid ÷ (fv + plain walk), particle ÷ hybrid)"
  echo
  $PY benchmarks/hybrid_value.py ellipse2d --arch cuda --steps 300 2>&1 | grep -v '^\[Taichi\]'
  echo
  $PY benchmarks/hybrid_value.py sphere3d --set 'cells=[64,64,64]' --arch cuda --steps 50 2>&1 | grep -v '^\[Taichi\]'
  echo
  $PY benchmarks/hybrid_value.py sphere3d --set 'cells=[128,128,128]' --arch cuda --steps 20 2>&1 | grep -v '^\[Taichi\]'
  echo
  echo "## The scenes (python -m ti_dk.scene NAME --arch cuda)"
  echo
  echo "| scene | wall s | max RSS KB | exit |"
  echo "|---|---|---|---|"
  for s in ellipse2d sphere3d; do
    /usr/bin/time -f "%e %M" -o "$tmp/$s.time" $PY -m ti_dk.scene "$s" --arch cuda --no-progress --out "$tmp" \
      > "$tmp/$s.log" 2>&1
    rc=$?
    read -r wall rss < "$tmp/$s.time" || true
    echo "| $s | ${wall:-?} | ${rss:-?} | $rc |"
  done
  echo
  for s in ellipse2d sphere3d; do
    echo "### $s: last lines of the run"
    echo
    echo '```'
    grep -v '^\[Taichi\]' "$tmp/$s.log" | tail -n 15
    echo '```'
    echo
  done
} | tee "$OUT"
