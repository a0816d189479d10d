#!/bin/bash
# Session 11 (particle helper): interleaved rounds of the particle rows, an old build against a new
# one, each run a fresh process; prints side, row, and the row's CPU and quality figures.
#   OLD=path/to/old/build NEW=path/to/new/build bench/session11_particle_rounds.sh [rounds]
# Simplification: bench_core's simplify_particle_1pct rows (wall ms, process CPU ms, points,
# err_avg_rel, cover_p95, within30). Resampling: bench_resample --side ours (cpu_ms, points, mesh
# mean / RMS / max, coverage p95, NN CV).
cd "$(dirname "$0")/.."
: "${OLD:?set OLD to the old build directory}" "${NEW:=build}"
export SURFEL_DATA=${SURFEL_DATA:-/work/shared/data}
rounds=${1:-3}
simplify_row() { "$1"/bin/bench_core --benchmark_filter="$2" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$3', b['name'].split('/iter')[0], round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)), '%.6g'%b.get('err_avg_rel',0), '%.6g'%b.get('cover_p95',0), '%.4g'%b.get('within30',0), flush=True)"; }
resample_row() { "$1"/bin/bench_resample --side ours --case "$2" 2>/dev/null | python3 -c "
import json,sys; t=sys.stdin.read(); j=json.loads(t[t.index('{'):])
keys=['cpu_ms','points','mesh_mean_rel','mesh_rms_rel','mesh_max_rel','coverage_p95_rel','nn_cv']
print('$3', '$2', ' '.join(str(j.get(k)) for k in keys), flush=True)"; }
for r in $(seq "$rounds"); do
  for f in '^simplify_particle_1pct/bunny_scans_merged/' '^simplify_particle_1pct/person_scan/'; do
    simplify_row "$OLD" "$f" old; simplify_row "$NEW" "$f" new
  done
  for c in bunny-x4 bunny_scan-x4 bunny_scan-half; do
    resample_row "$OLD" "$c" old; resample_row "$NEW" "$c" new
  done
done
