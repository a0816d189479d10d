#!/usr/bin/env python3
"""Interleaved A/B timing of whole processes: each round runs every command once, in order, so a
noisy stretch of a shared machine falls on all of them alike (hyperfine runs one command's
repetitions back to back). Prints, per command, the wall time (median and minimum, ms) and the
CPU time (user + system, median and minimum, ms), which moves least when other processes share
the cores; and the load average before and after.

    bench/ab_process.py --rounds 20 'old/surfel --version' 'build/bin/surfel --version'

Each command is split like a shell would split it (shlex) and run without a shell; its output is
discarded and a non-zero exit stops the run. Two untimed warm-up runs of each come first.
"""
import argparse
import os
import shlex
import statistics
import subprocess
import sys
import time


def run(args):
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = (time.perf_counter() - start) * 1000.0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        sys.exit(f"ab_process: {shlex.join(args)} exited {proc.returncode}")
    return wall, (usage.ru_utime + usage.ru_stime) * 1000.0


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("commands", nargs="+")
    a = p.parse_args()
    commands = [shlex.split(c) for c in a.commands]
    for args in commands:
        for _ in range(a.warmup):
            run(args)
    load_before = os.getloadavg()[0]
    samples = [[] for _ in commands]
    for _ in range(a.rounds):
        for i, args in enumerate(commands):
            samples[i].append(run(args))
    load_after = os.getloadavg()[0]
    width = max(len(c) for c in a.commands)
    print(f"{'command':<{width}}  wall median    min | cpu median    min   (ms, {a.rounds} interleaved rounds)")
    for text, s in zip(a.commands, samples):
        wall = [x[0] for x in s]
        cpu = [x[1] for x in s]
        print(f"{text:<{width}}  {statistics.median(wall):11.1f} {min(wall):6.1f} | "
              f"{statistics.median(cpu):10.1f} {min(cpu):6.1f}")
    print(f"load average {load_before:.2f} before, {load_after:.2f} after ({os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
