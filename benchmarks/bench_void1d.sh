#!/usr/bin/env bash
# Wall time of the paper's 20,000-member void1d ensemble to t = 0.01, one line per method.
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(mktemp -d)
for m in fv gaussian hybrid particle; do
  /usr/bin/time -f "$m: %e s wall, %M KB max RSS" python -m ti_dk.scene void1d --method "$m" --no-progress --out "$out" 2>&1 \
    | grep -v '^\[Taichi\]'
done
rm -rf "$out"
