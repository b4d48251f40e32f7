#!/usr/bin/env python3
"""How well the server's anchors agreed with an agent's own estimate, checked against ground truth.

The agent writes anchors.txt into its output folder (agent_rt/runtime/mapping_thread.cpp): after every
downlink message with a covisible map, its newest own keyframe (K) and every anchor it holds (A), with their
poses in the agent's world frame. For each message this compares the anchor's position relative to the
newest own keyframe with the same relative position in ground truth:

    error = | (T_w_k^-1 T_w_a).t - (G_k^-1 G_a).t |

so the agent's global drift cancels and what is left is how far the anchor sits from where the agent's current
estimate would put it. A consistent downlink keeps this near the server map's own local error (millimetres to a
centimetre); a wrong frame (T_m_w), a bad merge or a half-applied correction shows as centimetres.

Usage: anchor_consistency.py AGENT_OUTPUT DATASETS [--bin SECONDS]
  AGENT_OUTPUT  the agent's --output folder (holds anchors.txt)
  DATASETS      the folder holding agentN/ datasets with ground truth (the simulator's mission folder)
Standard library only.
"""
import argparse
import bisect
import math
import os
import sys

from cvislam_tools.files import read_groundtruth
from cvislam_tools.poses import quat_to_matrix, relative_translation


def load_ground_truth(datasets, agent):
    rows = read_groundtruth(os.path.join(datasets, "agent%d" % agent))
    if rows is None:
        raise FileNotFoundError("no ground truth for agent %d under %s (expected agent%d/mav0/state_groundtruth_"
                                "estimate0/data.csv)" % (agent, datasets, agent))
    return [t for t, _, _ in rows], [(quat_to_matrix(*q), list(p)) for _, p, q in rows]


def nearest(gt, t_ns, tolerance_ns=2_000_000):
    times, poses = gt
    i = bisect.bisect_left(times, t_ns)
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(times) and (best is None or abs(times[j] - t_ns) < abs(times[best] - t_ns)):
            best = j
    if best is None or abs(times[best] - t_ns) > tolerance_ns:
        return None
    return poses[best]


def percentile(values, q):
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("agent_output")
    parser.add_argument("datasets")
    parser.add_argument("--bin", type=float, default=5.0, help="seconds of sensor time per row (default 5)")
    args = parser.parse_args()
    path = os.path.join(args.agent_output, "anchors.txt")
    if not os.path.exists(path):
        sys.exit("no anchors.txt in %s: was the agent run with a server (--server)?" % args.agent_output)
    messages = {}  # (stream, sequence) -> (K, [A])
    order = []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            if line.startswith("#") or not line.strip():
                continue
            v = line.split()
            if len(v) != 13 or v[0] not in ("K", "A"):
                sys.exit("%s:%d: expected 13 fields starting with K or A" % (path, number))
            key = (int(v[1]), int(v[2]))
            qx, qy, qz, qw = map(float, v[9:13])  # TUM order: x, y, z, w
            entry = (int(v[3]), int(v[4]), int(v[5]), quat_to_matrix(qw, qx, qy, qz), [float(x) for x in v[6:9]])
            if key not in messages:
                messages[key] = [None, []]
                order.append(key)
            if v[0] == "K":
                messages[key][0] = entry
            else:
                messages[key][1].append(entry)
    gts = {}

    def gt_of(agent):
        if agent not in gts:
            gts[agent] = load_ground_truth(args.datasets, agent)
        return gts[agent]

    rows = []  # (t_s of the newest own keyframe, error_cm, anchor agent, own agent)
    for key in order:
        k, anchors = messages[key]
        if k is None or not anchors:
            continue
        agent, _, t_k, R_k, p_k = k
        g_k = nearest(gt_of(agent), t_k)
        if g_k is None:
            continue
        for a_agent, _, t_a, _, p_a in anchors:
            g_a = nearest(gt_of(a_agent), t_a)
            if g_a is None:
                continue
            est = relative_translation(R_k, p_k, p_a)
            truth = relative_translation(g_k[0], g_k[1], g_a[1])
            error = math.sqrt(sum((est[i] - truth[i]) ** 2 for i in range(3)))
            rows.append((t_k, error * 100.0, a_agent, agent))
    if not rows:
        sys.exit("anchors.txt holds no message with anchors that ground truth covers")
    own = rows[0][3]
    start = gt_of(own)[0][0]  # times from the start of the agent's sequence
    print("anchors against the agent's newest keyframe, relative position error vs ground truth [cm] (agent %d)" % own)
    print("%8s %8s %8s %8s %8s %8s %8s" % ("t[s]", "anchors", "own", "other", "p50", "p90", "max"))
    bins = {}
    for row in rows:
        bins.setdefault(int((row[0] - start) * 1e-9 // args.bin), []).append(row)
    for b in sorted(bins):
        r = bins[b]
        errors = [x[1] for x in r]
        print("%8.1f %8d %8d %8d %8.2f %8.2f %8.2f" % (b * args.bin, len(r), sum(1 for x in r if x[2] == own),
                                                   sum(1 for x in r if x[2] != own), percentile(errors, 0.5),
                                                   percentile(errors, 0.9), max(errors)))
    errors = [x[1] for x in rows]
    print("%8s %8d %8s %8s %8.2f %8.2f %8.2f" % ("all", len(rows), "", "", percentile(errors, 0.5),
                                                 percentile(errors, 0.9), max(errors)))


if __name__ == "__main__":
    main()
