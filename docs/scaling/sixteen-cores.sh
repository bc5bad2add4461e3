#!/usr/bin/env bash
# The issue-31 figures on a many-core host, in one call (docs/scaling.md, "Finer batches",
# "Stints"): threads 1..all cores in one process, and 1, 2, 4, 8 workers of 2 threads each, at
# the defaults (64 batches a pass, stints of 8 directions) and with stints of one direction (the
# sums before), so that the two are compared on the same machine, in the same session; then 1,
# 2, 4, 8 workers as processes of their own (`--worker-processes`), as the issue measured them.
#
#   bash docs/scaling/sixteen-cores.sh [VLF] [OUT] [L] [N]
#
# VLF is a release build of `vlf` (default target/release/vlf), OUT a folder for the three
# Markdown reports (default .), L and N the job's shape (default 2049 and 128: the Cornell box
# at the issue's settings; about 8 minutes on 16 cores, an estimate). Every run of a report is
# checked to give the first run's bits; the reports give medians, speed-ups and Amdahl's serial
# fraction.
set -euo pipefail
VLF=${1:-target/release/vlf}
OUT=${2:-.}
L=${3:-2049}
N=${4:-128}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
mkdir -p "$OUT"
shape=(--directions "$L" --resolution "$N")

echo "== the defaults: threads, and 1, 2, 4, 8 workers"
"$VLF" bench "$ROOT/scenes/cornell.obj" "${shape[@]}" --scaling --workers 1,2,4,8 \
    --worker-threads 2 --repeat 3 --out "$OUT/scaling-defaults.md"

echo "== stints of one direction: 1 and all threads, 1 and 8 workers (the sums before)"
CORES=$(nproc)
"$VLF" bench "$ROOT/scenes/cornell.obj" "${shape[@]}" --scaling --scale-threads "1,$CORES" \
    --workers 1,8 --worker-threads 2 --repeat 2 --stint-directions 1 \
    --out "$OUT/scaling-stints-of-1.md"

echo "== the defaults: 1, 2, 4, 8 worker processes (each building its own geometry)"
# The workers open the store themselves: a directory, in memory where /dev/shm is.
STORE=$(mktemp -d /dev/shm/vlf-bench-XXXXXX 2>/dev/null || mktemp -d)
trap 'rm -rf "$STORE"' EXIT
"$VLF" bench "$ROOT/scenes/cornell.obj" "${shape[@]}" --scaling --scale-threads 1 --workers 1,2,4,8 \
    --worker-threads 2 --repeat 2 --worker-processes --store "$STORE" \
    --out "$OUT/scaling-worker-processes.md"

echo "== reports in $OUT"
