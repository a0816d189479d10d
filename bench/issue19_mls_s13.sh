#!/bin/bash
# Issue 19.5 (session 13): MLS, Surfel against PCL on the clean bunny and every raw scan with a mesh,
# at several supports, each row a fresh process; prints program, row, env, wall ms, process CPU ms,
# h, radius, projected points, mean distance to the mesh. OLD=dir holding an older bench_core (its
# rows where it knows the dataset), ROUNDS (default 3), DATA (default: all six), SPECS (Surfel rows
# as "row|env" words; default below), PCL (PCL rows, the same form; default r10 r15 r20 at 2 threads,
# r10 and r20 at PCL's own default of 1: SURFEL_BENCH_PCL_THREADS=1). Set SURFEL_DATA to
# ../shared/data when the checkout is not beside it.
cd "$(dirname "$0")/.."
row() {  # binary filter [env]
  env $3 $1 --benchmark_filter="^$2/" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys
d=json.load(sys.stdin)['benchmarks']
if not d: sys.exit(0)
b=d[0]
print('$1', b['name'].split('/iter')[0], '$3' or '-', round(b['real_time'],1), round(b['cpu_time'],1), 'h=%.4g r=%.4g'%(b.get('h',0),b.get('radius',0)), 'pts=%d'%b.get('points',0), 'mean=%.4g'%b['mesh_mean'], flush=True)"
}
SPECS=${SPECS:-"mls_project_c15| mls_project_c20| mls_project_c20|SURFEL_BENCH_MLS_H=1.5 mls_project_c20|SURFEL_BENCH_MLS_H=0.5 mls_project|"}
PCL=${PCL-"mls_project_pcl_r10| mls_project_pcl_r15| mls_project_pcl_r20| mls_project_pcl_r10|SURFEL_BENCH_PCL_THREADS=1 mls_project_pcl_r20|SURFEL_BENCH_PCL_THREADS=1"}
for r in $(seq ${ROUNDS:-3}); do for d in ${DATA:-bunny bunny_scan bunny_scan_045 bunny_scans_merged dragon_scan buddha_scan}; do
  for spec in $SPECS; do
    f=${spec%|*}; e=${spec#*|}
    [ -n "$OLD" ] && row "$OLD/bench_core" "$f/$d" "$e"
    row build-bench/bin/bench_core "$f/$d" "$e"
  done
  for spec in $PCL; do
    f=${spec%|*}; e=${spec#*|}
    row build-bench/bin/bench_peer_pcl "$f/$d" "$e"
  done
done; done
