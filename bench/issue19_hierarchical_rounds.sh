#!/bin/bash
# Issue 19.4: interleaved rounds of hierarchical clustering, each row a fresh process: ours full
# (normals + radii), ours positions only, ours positions only at CGAL's count (bench_core's
# -cgal-count rows), then CGAL (bench_peer_cgal), for 1 % and 10 % of both scans; with OLD set, the
# same three rows of an old build's bench_core before ours in every round. Prints one line a run
# (build, row, wall ms, process CPU ms, points, err_avg_rel, cover_p95, within30), then the medians
# over the rounds and the CGAL / ours ratios of the CPU medians. The load average goes with it.
# Usage: SURFEL_DATA=... [BIN=build-bench/bin] [OLD=<old bin dir>] [ROUNDS=5] [CHRT="chrt -f 10"] bench/issue19_hierarchical_rounds.sh
# (CHRT: each run at a real-time priority, so that on a loaded machine neither our worker thread
# nor CGAL waits for the scheduler: the CPU and wall figures of an idle machine, nearly)
cd "$(dirname "$0")/.."
: "${SURFEL_DATA:?set SURFEL_DATA}"
BIN=${BIN:-build-bench/bin}
ROUNDS=${ROUNDS:-5}
LOG=$(mktemp)
uptime
for r in $(seq "$ROUNDS"); do for pct in 1 10; do for d in bunny_scans_merged person_scan; do
  runs=()
  [ -n "$OLD" ] && runs+=("old $OLD/bench_core simplify_hierarchical" "old $OLD/bench_core simplify_hierarchical-positions"
                         "old $OLD/bench_core simplify_hierarchical-positions-cgal-count")
  runs+=("new $BIN/bench_core simplify_hierarchical" "new $BIN/bench_core simplify_hierarchical-positions"
         "new $BIN/bench_core simplify_hierarchical-positions-cgal-count" "cgal $BIN/bench_peer_cgal simplify_hierarchical")
  for x in "${runs[@]}"; do
    set -- $x
    $CHRT "$2" --benchmark_filter="^$3_${pct}pct/$d/" --benchmark_format=json 2>/dev/null | python3 -c "
import json,sys; b=json.load(sys.stdin)['benchmarks'][0]
print('$1', b['name'].split('/iter')[0], round(b['real_time'],1), round(b['cpu_time'],1), int(b.get('points',0)),
      '%.5g'%b.get('err_avg_rel',0), '%.5g'%b.get('cover_p95',0), '%.4g'%b.get('within30',0))"
  done; done; done; done | tee "$LOG"
uptime
python3 - "$LOG" <<'EOF'
import sys, statistics, collections
rows = collections.defaultdict(list)
info = {}
for line in open(sys.argv[1]):
    build, name, wall, cpu, pts, err, cover, w30 = line.split()
    rows[(build, name)].append((float(wall), float(cpu)))
    info[(build, name)] = (pts, err, cover, w30)
med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in rows.items()}
for (build, name), (w, c) in sorted(med.items(), key=lambda kv: (kv[0][1].split('/')[1], kv[0][1].split('_')[-1].split('/')[0], kv[0][0], kv[0][1])):
    pts, err, cover, w30 = info[(build, name)]
    cpus = ' / '.join('%.1f' % c_ for _, c_ in rows[(build, name)])
    print(f'{build:4} {name:62} wall {w:7.1f} cpu {c:7.1f} ms  ({cpus})  points {pts} err {err} cover {cover} within30 {w30}')
print('CGAL / ours, medians of CPU (of wall):')
for (build, name), (w, c) in sorted(med.items()):
    if build == 'cgal': continue
    tail = name.split('_', 2)[-1]  # <pct>pct/<dataset>
    key = ('cgal', 'simplify_hierarchical_' + tail)
    if key in med:
        print(f'  {build:4} {name:62} {med[key][1] / c:5.2f}x ({med[key][0] / w:5.2f}x)')
EOF
rm -f "$LOG"
