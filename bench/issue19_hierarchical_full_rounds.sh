#!/bin/bash
# Issue 19.4, session 15 (hierarchical helper): the full-output rows only (normals and radii),
# interleaved: an old build's bench_core, this build's, then CGAL (bench_peer_cgal), each a fresh
# process, for 1 % and 10 % of both scans. Prints build, row, wall ms, process CPU ms, points.
# Usage: SURFEL_DATA=... OLD=<old bin dir> [BIN=build-bench/bin] [ROUNDS=9] [CHRT="chrt -f 10"] bench/issue19_hierarchical_full_rounds.sh
cd "$(dirname "$0")/.."
: "${SURFEL_DATA:?set SURFEL_DATA}" "${OLD:?set OLD to the old bin directory}"
export SURFEL_DATA
BIN=${BIN:-build-bench/bin}
uptime
for r in $(seq "${ROUNDS:-9}"); do for pct in 1 10; do for d in bunny_scans_merged person_scan; do
  for x in "old $OLD/bench_core" "new $BIN/bench_core" "cgal $BIN/bench_peer_cgal"; do
    set -- $x
    $CHRT "$2" --benchmark_filter="^simplify_hierarchical_${pct}pct/$d/" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]; print('$1', '${pct}pct/$d', round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)))"
  done; done; done; done
uptime
