#!/bin/bash
# Issue 19.4 (session 9): interleaved rounds of iterative and particle simplification at 1 % of the
# merged scans, an old build against this one (OLD=path/to/old/build, default: none), each a fresh
# process; prints build, row, wall ms, process CPU ms, points, err_avg_rel, cover_p95, within30.
cd "$(dirname "$0")/.."
row() { "$1"/bin/bench_core --benchmark_filter="$2" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$1', b['name'].split('/iter')[0], round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)), '%.4g'%b.get('err_avg_rel',0), '%.4g'%b.get('cover_p95',0), '%.4g'%b.get('within30',0), flush=True)"; }
for r in 1 2 3; do
  for f in '^simplify_iterative_1pct/bunny_scans_merged' '^simplify_particle_1pct/bunny_scans_merged'; do
    [ -n "$OLD" ] && row "$OLD" "$f"
    row build "$f"
  done
done
