#!/usr/bin/env bash
# Issue 13's benchmarks and the two big scenes on the CUDA backend, written to one Markdown file.
#
#     bash benchmarks/gpu.sh [OUT.md]        (default: benchmarks/gpu_results.md)
#
# Needs a CUDA driver (ti_dk refuses --arch cuda without one). Each part's wall time includes
# start-up and JIT; the tables inside come from the benchmark scripts themselves (bench_speed.py
# reports the best of 3 blocks after a warm-up step). The NumPy row of bench_speed.py runs on the
# CPU in any case; its "threads" column means nothing on CUDA.
#
# Parts run most important first (a smoke run, issue 40's and 26's hybrid_value tables, then the throughput
# benchmarks, then the whole scenes), each under `timeout $PART_S` (default 600 s), so a lease
# shorter than the whole still brings back the tables that finished; the file is written as it goes.
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
PY=${PYTHON:-python}
OUT=${1:-benchmarks/gpu_results.md}
PART_S=${PART_S:-600}
part() { timeout "$PART_S" "$@" 2>&1 | grep -v '^\[Taichi\]'; echo "(exit ${PIPESTATUS[0]})"; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

{
  echo "# ti_dk on CUDA ($(date -u +%Y-%m-%d), $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $(git rev-parse --short HEAD 2>/dev/null))"
  echo
  echo "## Smoke: void1d, fv and hybrid, on CUDA"
  echo
  echo '```'
  part $PY -m ti_dk.scene void1d --method fv --ensemble 8 --t-end 0.0005 --no-frames --no-progress --out "$tmp"
  part $PY -m ti_dk.scene void1d --method hybrid --ensemble 8 --t-end 0.0005 --no-frames --no-progress --out "$tmp"
  echo '```'
  echo
  echo "## Issue 40's table on CUDA: whole runs, particle ÷ hybrid, the library's defaults (region from q̄)"
  echo
  Q="--set region_from=mean --set regrid_floor=0"
  for d in 30 100 300 1000; do
    part $PY benchmarks/hybrid_value.py ellipse2d --arch cuda --whole --particle-steps 30 $Q --set ppc_outer=$d --set ppc_inner=$((d / 2))
    echo
  done
  for d in 30 100 300; do
    part $PY benchmarks/hybrid_value.py sphere3d --arch cuda --whole --particle-steps 10 $Q --set 'cells=[64,64,64]' --set ppc_outer=$d --set ppc_inner=$((d / 2))
    echo
  done
  for d in 30 300; do  # the issue's GPU case: the hybrid against the particles on sphere3d 128³
    part $PY benchmarks/hybrid_value.py sphere3d --arch cuda --whole --particle-steps 5 $Q --set ppc_outer=$d --set ppc_inner=$((d / 2))
    echo
  done
  echo "### host syncs and bytes a step (the stopwatch as on a GPU: every 16th step timed)"
  echo
  part $PY benchmarks/readback.py ellipse2d --arch cuda --steps 300 $Q
  echo
  part $PY benchmarks/readback.py sphere3d --arch cuda --steps 100 $Q --set 'cells=[64,64,64]'
  echo
  echo "## hybrid_value.py --arch cuda (issue 26: hybrid ÷ (fv + plain walk), particle ÷ hybrid)"
  echo
  part $PY benchmarks/hybrid_value.py ellipse2d --arch cuda --steps 300
  echo
  part $PY benchmarks/hybrid_value.py sphere3d --set 'cells=[64,64,64]' --arch cuda --steps 50
  echo
  part $PY benchmarks/hybrid_value.py sphere3d --set 'cells=[128,128,128]' --arch cuda --steps 20
  echo
  echo "### where the GPU hybrid's step goes (kernel profiler on: it adds to every launch)"
  echo
  part $PY benchmarks/hybrid_value.py ellipse2d --arch cuda --steps 100 --kernels
  echo
  echo "## bench_speed.py --arch cuda"
  echo
  part $PY benchmarks/bench_speed.py --arch cuda --threads 1
  echo
  echo "## bench_fv.py --arch cuda"
  echo
  part $PY benchmarks/bench_fv.py --arch cuda
  echo
  echo "## bench_hybrid.py --arch cuda"
  echo
  part $PY benchmarks/bench_hybrid.py --arch cuda
  echo
  echo "## The scenes (python -m ti_dk.scene NAME --arch cuda)"
  echo
  echo "| scene | wall s | max RSS KB | exit |"
  echo "|---|---|---|---|"
  for s in ellipse2d sphere3d; do
    t0=$SECONDS; rss=?
    if [ -x /usr/bin/time ]; then
      /usr/bin/time -f "%M" -o "$tmp/$s.time" timeout "$PART_S" $PY -m ti_dk.scene "$s" --arch cuda --no-progress \
        --out "$tmp" > "$tmp/$s.log" 2>&1
      rc=$?; read -r rss < "$tmp/$s.time" || true
    else
      timeout "$PART_S" $PY -m ti_dk.scene "$s" --arch cuda --no-progress --out "$tmp" > "$tmp/$s.log" 2>&1
      rc=$?
    fi
    wall=$((SECONDS - t0))
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
