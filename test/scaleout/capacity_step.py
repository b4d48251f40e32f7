#!/usr/bin/env python3
"""One step of test/scaleout/capacity_bench.sh, summed up as one JSON line on stdout.

Reads the step's folder: m<i>.json (each replay client's report), out<r>/stats.json and out<r>/ingest_ms.csv (each
replica's view), out<r>/<mission>/backend.json and recognition.json (the back-end and place recognition), and
replica<r>.json (what the script measured of each replica: CPU seconds, peak memory, its cgroup's cpu.stat).
"""
import csv
import glob
import json
import os
import sys


def pct(values, q):
    """Nearest-rank percentile, as the server's own."""
    if not values:
        return None
    v = sorted(values)
    return v[max(0, min(len(v) - 1, int(-(-q * len(v) // 1)) - 1))]


def main():
    step, missions, replicas, bound = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    wall, replays_ok, budget = float(sys.argv[5]), sys.argv[6] == "1", float(sys.argv[7])
    machine_busy = float(sys.argv[8]) if len(sys.argv) > 8 else None
    ok = replays_ok
    agents = []
    for m in range(missions):
        try:
            agents += json.load(open(f"{step}/m{m}.json"))["agents"]
        except (OSError, ValueError, KeyError):
            ok = False
    ack = [x for a in agents for x in a.get("ack_ms", [])]
    served, samples, merges, gbas, recog, measured = [], [], [], [], [], []
    for r in range(replicas):
        out = f"{step}/out{r}"
        try:
            served += [a for a in json.load(open(f"{out}/stats.json"))["agents"]
                       if int(a["ingest_ms"]["samples"]) > 0]
            with open(f"{out}/ingest_ms.csv") as f:
                samples += [float(row["ingest_ms"]) for row in csv.DictReader(f)]
        except (OSError, ValueError, KeyError):
            ok = False
        for path in glob.glob(f"{out}/*/backend.json"):
            b = json.load(open(path))
            merges += b.get("merges", [])
            gbas += b.get("gba", [])
        for path in glob.glob(f"{out}/*/recognition.json"):
            recog.append(json.load(open(path)))
        try:
            measured.append(json.load(open(f"{step}/replica{r}.json")))
        except (OSError, ValueError):
            ok = False
    finished = ok and bool(agents) and all(a["finished"] for a in agents) and len(served) >= len(agents)
    worst = max((a["ingest_ms"]["p99"] for a in served), default=float("inf"))
    during_gba = [a["ingest_during_gba_ms"] for a in served if int(a["ingest_during_gba_ms"]["samples"]) > 0]
    merged = [m["match_to_merged_s"] for m in merges if m.get("match_to_merged_s", -1) >= 0]
    optimised = [m["match_to_optimised_s"] for m in merges if m.get("match_to_optimised_s", -1) >= 0]
    cpu = sum(x["cpu_s"] for x in measured)
    try:
        postgres_cpu = json.load(open(f"{step}/postgres.json"))["cpu_s"]
    except (OSError, ValueError, KeyError):
        postgres_cpu = None
    row = {
        "replicas": replicas, "agents": len(agents), "missions": missions, "finished": bool(finished),
        "ingest_ms_p50_median": pct([a["ingest_ms"]["p50"] for a in served], 0.5),
        "ingest_ms_p99_worst": worst,
        "ingest_ms_p99_pooled": pct(samples, 0.99), "ingest_ms_max_pooled": max(samples, default=None),
        "ingest_samples": len(samples),
        "ingest_during_gba_ms_p99_worst": max((g["p99"] for g in during_gba), default=None),
        "ack_ms_p50": pct(ack, 0.5), "ack_ms_p99": pct(ack, 0.99),
        "batches": sum(a["batches"] for a in agents), "acked": sum(a["acked"] for a in agents),
        "redirects": sum(a["redirects"] for a in agents), "wall_s": wall,
        "server_cpu_s": round(cpu, 1),
        "postgres_cpu_s": postgres_cpu,  # its backends for the step's database
        "replica_cpu_budget": budget or None,
        # The replicas' use of what their budget allowed over the step (1: every period's quota spent).
        "budget_used": round(cpu / (budget * replicas * wall), 2) if budget > 0 and wall > 0 else None,
        "machine_busy": machine_busy,  # the whole machine's busy share over the step (all processes)
        "throttled_periods": sum(x.get("nr_throttled", 0) for x in measured),
        "periods": sum(x.get("nr_periods", 0) for x in measured),
        "throttled_s": round(sum(x.get("throttled_s", 0.0) for x in measured), 1),
        "replica_rss_mb_max": max((x["rss_mb"] for x in measured), default=None),
        "replica_rss_mb_sum": round(sum(x["rss_mb"] for x in measured), 1),
        # What the replicas held at the end (after redundancy removal), for memory per keyframe and point.
        "server_keyframes": sum(int(a.get("server_keyframes", 0)) for a in served),
        "server_points": sum(int(a.get("points", 0)) for a in served),
        "uplink_bytes": sum(int(a.get("up", {}).get("message", {}).get("bytes", 0)) for a in served),
        "downlink_bytes": sum(int(a.get("down", {}).get("message", {}).get("bytes", 0)) for a in served),
        "merges": len(merges),
        "match_to_merged_s_p50": pct(merged, 0.5), "match_to_merged_s_p99": pct(merged, 0.99),
        "match_to_optimised_s_p50": pct(optimised, 0.5), "match_to_optimised_s_p99": pct(optimised, 0.99),
        "gba_runs": len(gbas), "gba_keyframes_max": max((g["keyframes"] for g in gbas), default=0),
        "gba_solve_s_max": max((g["solve_s"] for g in gbas), default=0.0),
        "gba_solve_s_total": round(sum(g["solve_s"] for g in gbas), 1),
        "recognition_queries": sum(x.get("queries", 0) for x in recog),
        "recognition_busy_s": round(sum(x.get("busy_s", 0.0) for x in recog), 1),
        "recognition_dropped_events": sum(x.get("dropped_events", 0) for x in recog),
        "keeps_up": bool(finished and worst <= bound),
        # Who flew, by the replay clients' reports, and whom the replicas served, per mission.
        "agent_ids": sorted({a["agent"] for a in agents}),
        "served_agents": {m: sorted(a["agent_id"] for a in served if a["mission"] == m)
                          for m in sorted({a["mission"] for a in served})},
        "ingest_ms_samples": [round(x, 3) for x in samples],
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()
