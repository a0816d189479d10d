#!/bin/bash
# Issue 19.4, session 11 (hierarchical helper): interleaved rounds of hierarchical clustering,
# positions only (what CGAL returns), an old build against this one, and CGAL. For each round,
# target and dataset: OLD positions at the percentage's count, new positions at that count, new
# positions at CGAL's count (the -cgal-count rows), CGAL; each a fresh process. Prints build,
# benchmark, wall ms, process CPU ms, points, err_avg_rel, cover_p95 (5 digits).
# Usage: OLD=<old build dir> ROUNDS=3 SURFEL_DATA=... bench/issue19_hierarchical_h11.sh
cd "$(dirname "$0")/.."
OLD=${OLD:?set OLD to the old build directory}
for r in $(seq "${ROUNDS:-3}"); do for pct in 1 10; do for d in bunny_scans_merged person_scan; do
  for x in "$OLD bench_core simplify_hierarchical-positions" "build bench_core simplify_hierarchical-positions" \
           "build bench_core simplify_hierarchical-positions-cgal-count" "build bench_peer_cgal simplify_hierarchical"; do
    set -- $x
    "$1/bin/$2" --benchmark_filter="^$3_${pct}pct/$d" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$r', '$1' if '$1' == 'build' else 'old', '$2', b['name'].split('/iter')[0], round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)), '%.5g'%b.get('err_avg_rel',0), '%.5g'%b.get('cover_p95',0))"
  done; done; done; done
