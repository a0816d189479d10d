#!/bin/bash
# Issue 19.5 (session 10): interleaved rounds of MLS on bunny_scan and bunny, an old bench_core
# (OLD=dir holding it, default: none) against this build's and PCL's, at the supports of
# bench/README.md's table, each a fresh process; prints program, row, env, wall ms, process CPU
# ms, h, radius, points, mean distance to the mesh. ROUNDS (default 3), DATA (default
# "bunny_scan bunny").
cd "$(dirname "$0")/.."
row() {  # binary filter [env]
  env $3 $1 --benchmark_filter="^$2/" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$1', b['name'].split('/iter')[0], '$3', round(b['real_time'],1), round(b['cpu_time'],1), 'h=%.4g r=%.4g'%(b.get('h',0),b.get('radius',0)), 'pts=%d'%b.get('points',0), 'mean=%.4g rel=%.4g'%(b['mesh_mean'],b['mesh_mean_rel']), flush=True)"
}
for r in $(seq ${ROUNDS:-3}); do for d in ${DATA:-bunny_scan bunny}; do
  for spec in "mls_project_c15/$d|" "mls_project_c20/$d|" "mls_project_c20/$d|SURFEL_BENCH_MLS_H=1.5" \
              "mls_project_c20/$d|SURFEL_BENCH_MLS_H=0.5" "mls_project/$d|"; do
    f=${spec%|*}; e=${spec#*|}
    [ -n "$OLD" ] && row "$OLD/bench_core" "$f" "$e"
    row build/bin/bench_core "$f" "$e"
  done
  for f in mls_project_pcl_r10 mls_project_pcl_r15 mls_project_pcl_r20; do row build/bin/bench_peer_pcl "$f/$d"; done
done; done
