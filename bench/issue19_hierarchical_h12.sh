#!/bin/bash
# Issue 19.4, session 12 (hierarchical helper): interleaved fresh processes of one hierarchical
# Simplify call (positions only, at CGAL's counts: bench_core's -cgal-count rows), an old build's
# libraries against a new one's (bench/issue19_hierarchical_call.cpp linked against each). Prints
# round, case, build, then the driver's wall ms, process CPU ms, page faults and points.
# Usage: OLD=<old build dir> NEW=<new build dir> ROUNDS=7 SURFEL_DATA=... bench/issue19_hierarchical_h12.sh
set -e
cd "$(dirname "$0")/.."
OLD=${OLD:?set OLD to the old build directory}
NEW=${NEW:-build-bench}
D=${SURFEL_DATA:?set SURFEL_DATA}
T=$(mktemp -d)
for v in OLD NEW; do
  B=${!v}
  c++ -Icore -isystem /usr/include/eigen3 -O2 -std=c++20 -o "$T/$v" bench/issue19_hierarchical_call.cpp \
    "$B"/lib/libsurfel_simplify.a "$B"/lib/libsurfel_resample.a "$B"/lib/libsurfel_io.a -ldl \
    "$B"/lib/libsurfel_surface.a "$B"/lib/libsurfel_spatial.a "$B"/lib/libsurfel_base.a -llz4 -ltbb -lpthread
done
for r in $(seq "${ROUNDS:-7}"); do
  for c in "bunny_scans_merged 3627 merged-1" "person_scan 2431 person-1" "bunny_scans_merged 36122 merged-10" \
           "person_scan 24550 person-10"; do
    set -- $c
    for v in OLD NEW; do echo "$r $3 $v $("$T/$v" "$D/$1.ply" "$2" 1)"; done
  done
done
rm -rf "$T"
