#!/usr/bin/env python3
"""Markdown tables of capacity_bench.sh results, as docs/results/capacity.md gives them.

    test/scaleout/capacity_table.py out/bench/capacity.json [more.json ...] [--mission]

One row per step of every file, in order. --mission: the columns of a single growing mission (the back-end's
latency, GBA and memory) instead of those of the replica comparison.
"""
import json
import sys


def f(v, digits=0):
    return "-" if v is None else f"{v:.{digits}f}"


def main():
    files = [a for a in sys.argv[1:] if not a.startswith("--")]
    mission = "--mission" in sys.argv
    if mission:
        print("| agents | ingest p99 worst / pooled [ms] | ack p50 / p99 [ms] | replica CPU [s] (budget used) | "
              "merges, match -> merged / optimised p99 [s] | GBA runs, largest [KFs], its solve [s] | "
              "recognition queries, dropped | keyframes held | RSS [MB] | keeps up |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    else:
        print("| replicas | agents (missions) | ingest p50 [ms] | ingest p99 worst agent / pooled [ms] | "
              "ack p50 / p99 [ms] | replicas' CPU [s] in wall [s] | budget used, periods throttled | "
              "machine busy | keeps up |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in files:
        for s in json.load(open(path))["steps"]:
            keeps = "yes" if s["keeps_up"] else "**no**"
            if mission:
                print(f"| {s['agents']} | {f(s['ingest_ms_p99_worst'], 1)} / {f(s['ingest_ms_p99_pooled'])} | "
                      f"{f(s['ack_ms_p50'])} / {f(s['ack_ms_p99'])} | {s['server_cpu_s']} ({f(s['budget_used'], 2)}) | "
                      f"{s['merges']}, {f(s['match_to_merged_s_p99'], 2)} / {f(s['match_to_optimised_s_p99'], 1)} | "
                      f"{s['gba_runs']}, {s['gba_keyframes_max']}, {f(s['gba_solve_s_max'], 1)} | "
                      f"{s['recognition_queries']}, {s['recognition_dropped_events']} | "
                      f"{s.get('server_keyframes', '-')} | {f(s['replica_rss_mb_max'])} | {keeps} |")
            else:
                throttled = "-" if not s["replica_cpu_budget"] else \
                    f"{f(s['budget_used'], 2)}, {100 * s['throttled_periods'] / max(1, s['periods']):.0f} %"
                print(f"| {s['replicas']} | {s['agents']} ({s['missions']}) | {f(s['ingest_ms_p50_median'])} | "
                      f"{f(s['ingest_ms_p99_worst'], 1)} / {f(s['ingest_ms_p99_pooled'])} | "
                      f"{f(s['ack_ms_p50'])} / {f(s['ack_ms_p99'])} | {s['server_cpu_s']} in {s['wall_s']} | "
                      f"{throttled} | {f(s.get('machine_busy'), 2)} | {keeps} |")


if __name__ == "__main__":
    main()
