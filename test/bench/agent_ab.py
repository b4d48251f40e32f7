#!/usr/bin/env python3
"""Two cvislam_agent binaries side by side on one sequence: runs them alternately (A, B, A, B, ...) so that both
see the same machine, and reports per binary the CPU time of the process (user + system, from wait4), the wall
time, and the p50/p99 of tracking and of the keyframe hand-over to mapping from each run's latency.json, as the
median over the runs. Writes the raw figures of every run to --json.

  test/bench/agent_ab.py --a OLD_BIN --b NEW_BIN --dataset SEQ [--runs 5] [--pace realtime] [--json OUT.json]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

STAGES = ("tracking_total", "keyframe_publish_to_receive", "mapping_total")


def run_once(binary, dataset, pace, extra):
    with tempfile.TemporaryDirectory(prefix="agent_ab_") as out:
        args = [binary, "--dataset", dataset, "--output", out, "--pace", pace, "--quiet", *extra]
        started = os.times().elapsed
        process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        _, status, usage = os.wait4(process.pid, 0)
        wall_s = os.times().elapsed - started
        stderr = process.stderr.read()
        process.stderr.close()
        if os.waitstatus_to_exitcode(status) != 0:
            sys.exit(f"agent_ab: {binary} failed ({os.waitstatus_to_exitcode(status)}): {stderr[-2000:]}")
        with open(os.path.join(out, "latency.json"), encoding="utf-8") as f:
            latency = json.load(f)
        with open(os.path.join(out, "summary.json"), encoding="utf-8") as f:
            summary = json.load(f)
    row = {"cpu_s": usage.ru_utime + usage.ru_stime, "wall_s": wall_s, "frames": summary["frames"],
           "keyframes": summary["keyframes"]}
    for stage in STAGES:
        row[f"{stage}_p50_ms"] = latency[stage]["p50_ms"]
        row[f"{stage}_p99_ms"] = latency[stage]["p99_ms"]
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--a", required=True, help="the first cvislam_agent binary (e.g. the old one)")
    parser.add_argument("--b", required=True, help="the second cvislam_agent binary")
    parser.add_argument("--dataset", required=True, help="a EuRoC/ASL sequence folder (the one holding mav0)")
    parser.add_argument("--runs", type=int, default=5, help="runs per binary (default 5)")
    parser.add_argument("--pace", default="realtime", help="the agent's --pace (default realtime)")
    parser.add_argument("--json", help="write every run's figures here")
    parser.add_argument("extra", nargs="*", help="more agent options, after --")
    args = parser.parse_args()
    for binary in (args.a, args.b):
        if not os.access(binary, os.X_OK):
            sys.exit(f"agent_ab: {binary} is not an executable")
    runs = {"a": [], "b": []}
    for i in range(args.runs):
        for key in ("a", "b"):
            row = run_once(getattr(args, key), args.dataset, args.pace, args.extra)
            runs[key].append(row)
            print(f"run {i + 1}/{args.runs} {key}: cpu {row['cpu_s']:.2f} s, tracking p50 "
                  f"{row['tracking_total_p50_ms']:.2f} ms", file=sys.stderr, flush=True)
    columns = ["cpu_s", "wall_s"] + [f"{s}_{q}_ms" for s in STAGES for q in ("p50", "p99")]
    print(f"{'median of ' + str(args.runs) + ' runs':<40} {'A':>10} {'B':>10} {'B/A':>7}")
    for column in columns:
        a = statistics.median(r[column] for r in runs["a"])
        b = statistics.median(r[column] for r in runs["b"])
        print(f"{column:<40} {a:>10.3f} {b:>10.3f} {b / a if a else float('nan'):>7.3f}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"a": args.a, "b": args.b, "dataset": args.dataset, "pace": args.pace, "runs": runs}, f,
                      indent=2)


if __name__ == "__main__":
    main()
