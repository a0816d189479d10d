#!/bin/bash
# Issue 19.5: interleaved rounds of MLS, Surfel and PCL at several supports (see bench_core.cpp and
# bench_peer_pcl.cpp); prints wall ms, process CPU ms, h, radius, points, mean distance to bunny_mesh.
cd "$(dirname "$0")/.."
row() {  # program filter [env]
  env $3 build/bin/$1 --benchmark_filter="^$2/" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$1', b['name'].split('/iter')[0], '$3', round(b['real_time'],1), round(b['cpu_time'],1), 'h=%.4g r=%.4g'%(b.get('h',0),b.get('radius',0)), 'pts=%d'%b.get('points',0), 'mean=%.4g rel=%.4g rms=%.4g'%(b['mesh_mean'],b['mesh_mean_rel'],b['mesh_rms']))"
}
for r in 1 2 3; do for d in bunny_scan bunny; do
  row bench_core mls_project/$d
  row bench_core mls_project_c20/$d
  row bench_core mls_project_c15/$d
  row bench_core mls_project/$d "SURFEL_BENCH_MLS_H=0.75"
  row bench_core mls_project_c20/$d "SURFEL_BENCH_MLS_H=1.5"
  row bench_peer_pcl mls_project/$d
  row bench_peer_pcl mls_project_pcl_r10/$d
  row bench_peer_pcl mls_project_pcl_r15/$d
  row bench_peer_pcl mls_project_pcl_r20/$d
done; done
