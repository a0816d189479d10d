#!/bin/bash
# Issue 19.4: interleaved rounds of hierarchical clustering (ours full, ours positions only, CGAL),
# each a fresh process; prints wall ms, process CPU ms, points, err_avg_rel, cover_p95, within30, mesh_mean.
# Interleaved rounds: ours (full), ours (positions only), CGAL; each a fresh process.
cd "$(dirname "$0")/.."
for r in 1 2 3 4 5; do for pct in 1 10; do for d in bunny_scans_merged person_scan; do
  for x in "bench_core simplify_hierarchical" "bench_core simplify_hierarchical-positions" "bench_peer_cgal simplify_hierarchical"; do
    set -- $x
    build/bin/$1 --benchmark_filter="^$2_${pct}pct/$d" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$1', b['name'].split('/iter')[0], round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)), '%.4g'%b.get('err_avg_rel',0), '%.4g'%b.get('cover_p95',0), '%.4g'%b.get('within30',0), '%.4g'%b.get('mesh_mean',0))"
  done; done; done; done
