#!/usr/bin/python3
"""Scores a finished mission (deploy/run_mission.sh) and reports it: tables on stdout, OUT/summary.json with the
same figures, and OUT/report/index.html with SVG pictures beside the tables.

    mission_report.py --out OUT --eval BUILD/bin/cvislam_eval

Reads OUT/mission.json, OUT/agents/<agent>/ (trajectory.txt, latency.json, link.json, link_timeline.csv),
OUT/server/ (stats.json, timeline.csv, <mission>/keyframes_agent<N>.txt) and the mission's ground truth
(the simulator's EuRoC folders). Only the Python standard library."""

import argparse
import bisect
import csv
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mission_pictures  # noqa: E402  (tools/mission_pictures.py: the SVGs and the HTML page)
from cvislam_tools import evaluation  # noqa: E402
from cvislam_tools.evaluation import ate  # noqa: E402
from cvislam_tools.files import load_json, read_groundtruth, read_rows  # noqa: E402
from cvislam_tools.poses import angle_between_deg, eval_transform, pose_apply, pose_inv, pose_mul  # noqa: E402


def run_eval(eval_bin, pairs, json_path, align=None, per_pose=False):
    """cvislam_eval over (estimate, ground truth) pairs; returns its JSON, or None with the reason printed."""
    result, reason = evaluation.run_eval(eval_bin, pairs, json_path, align, per_pose)
    if result is None:
        print(f"  (not evaluated: {reason})")
    return result


def counter(stats_map, kind):
    c = stats_map.get(kind, {})
    return int(c.get("messages", 0)), int(c.get("bytes", 0))


def ms(value):
    """Milliseconds to one decimal, or '-' when the server did not record them (an older server)."""
    return "-" if value is None else f"{value:.1f}"


def cm(value):
    return "   n/a" if value is None or math.isnan(value) else f"{value * 100:6.2f}"


def largest_live_step_mm(path, after_s=0.0):
    """The largest jump of tracking's live position between frames beyond constant velocity (the second
    difference of trajectory_online.txt), in mm, from `after_s` seconds into the run on (the IMU initialisation
    moves the world frame once, before): what a correction or an anchor would show as a step."""
    rows = read_rows(path, None, 4)
    if rows is None:
        return None
    positions = [r[1:4] for r in rows if r[0] - rows[0][0] >= after_s]
    steps = [sum((positions[i][k] - 2 * positions[i - 1][k] + positions[i - 2][k]) ** 2 for k in range(3)) ** 0.5
             for i in range(2, len(positions))]
    return 1000.0 * max(steps) if steps else None


def report_downlink_use(out, mission, summary):
    """What each agent's mapping did with the downlink (summary.json "downlink")."""
    rows = []
    for a in mission["agents"]:
        agent = load_json(os.path.join(out, "agents", a, "summary.json"))
        if agent is None or "downlink" not in agent:
            continue
        d = agent["downlink"]
        row = {"agent": a, **d, "keyframes": agent.get("keyframes", 0),
               "largest_live_step_mm": largest_live_step_mm(os.path.join(out, "agents", a, "trajectory_online.txt"),
                                                            max(0.0, float(agent.get("imu_initialised_at_s", 0))) + 1.0)}
        rows.append(row)
    if not rows:
        return
    summary["downlink_use"] = rows
    print("the downlink in the agents' mapping: anchors (the server's keyframes held fixed in local BA) and corrections "
          "of own keyframes")
    print(f"{'agent':8} {'anchors in':>10} {'out':>5} {'most held':>9} {'points':>7} {'local BAs with anchors':>23} "
          f"{'corrections now/later':>21} {'largest[cm, deg]':>17} {'live step max[mm]':>17}")
    print("  (live step: tracking's largest jump between frames beyond constant velocity, from 1 s after the IMU "
          "initialisation on)")
    for r in rows:
        step = r["largest_live_step_mm"]
        print(f"{r['agent']:8} {r['anchors_added']:10d} {r['anchors_released']:5d} {r['most_anchors_held']:9d} "
              f"{r['anchor_points_added']:7d} {r['local_ba_with_anchors']:11d} of {r['keyframes']:<8d} "
              f"{r['corrections_applied']:10d}/{r['corrections_deferred']:<10d} "
              f"{100 * r['largest_correction_m']:8.2f}, {r['largest_correction_deg']:6.3f} "
              f"{step if step is not None else float('nan'):17.1f}")
    refused = sum(int(r["refused"]) for r in rows)
    if refused:
        print(f"  downlink messages mapping refused: {refused} (see the agents' logs)")


def nearest_rank(sorted_values, p):
    """The p-quantile (p in (0, 1]) of sorted values by nearest rank."""
    return sorted_values[min(len(sorted_values), max(1, math.ceil(p * len(sorted_values)))) - 1]


def spread(values):
    """'n, p50, p99, max' of seconds (nearest rank), or 'none'."""
    if not values:
        return "none"
    v = sorted(values)
    return f"{len(v)}: p50 {nearest_rank(v, 0.5):.2f} s, p99 {nearest_rank(v, 0.99):.2f} s, max {v[-1]:.2f} s"


def report_backend(out, mission, server_agents, summary):
    """The server's back-end (backend.json) and how long the server took to store each batch meanwhile."""
    name = mission["mission"]
    backend = load_json(os.path.join(out, "server", name, "backend.json"))
    print()
    print("== server back-end: merges, loops, global BA, redundancy removal (backend.json), and ingest while it ran")
    section = {}
    if backend is not None:
        gba = [g for g in backend.get("gba", []) if not g.get("cancelled")]
        biggest = max((g["keyframes"] for g in gba), default=0)
        section = {"merges": len(backend.get("merges", [])), "loops": len(backend.get("loops", [])),
                   "gba_runs": len(gba), "gba_cancelled": backend.get("gba_cancelled", 0),
                   "gba_solve_s_max": max((g["solve_s"] for g in gba), default=None), "gba_largest_keyframes": biggest,
                   "redundant_keyframes_removed": backend.get("redundant_keyframes_removed", 0),
                   "redundancy_checked": backend.get("redundancy_checked", 0),
                   "redundant_removed_by_final_pass": backend.get("redundant_removed_by_final_pass", 0),
                   "redundant_kept_for_imu_gap": backend.get("redundant_kept_for_imu_gap", 0),
                   "new_keyframes_fused": backend.get("new_keyframes_fused", 0),
                   "new_keyframe_links": backend.get("new_keyframe_links", 0),
                   "new_keyframe_point_merges": backend.get("new_keyframe_point_merges", 0),
                   "new_keyframe_fuse_ms_mean": backend.get("new_keyframe_fuse_ms_mean", 0.0),
                   "new_keyframe_fuse_ms_max": backend.get("new_keyframe_fuse_ms_max", 0.0),
                   "new_keyframe_fuse_locked_ms_max": backend.get("new_keyframe_fuse_locked_ms_max", 0.0)}
        print(f"merges {section['merges']}, loops closed {section['loops']}; GBA {len(gba)} runs (largest "
              f"{biggest} KFs, solve max {section['gba_solve_s_max'] or 0:.2f} s), {section['gba_cancelled']} cut short "
              f"by a newer change; redundant KFs removed {section['redundant_keyframes_removed']} of "
              f"{section['redundancy_checked']} checked ({section['redundant_removed_by_final_pass']} by the final pass; "
              f"{section['redundant_kept_for_imu_gap']} redundant kept for the 2 s IMU gap)")
        windowed = [g for g in gba if g.get("windowed")]
        section["gba_windowed"] = len(windowed)
        if windowed:
            parts = ", ".join(f"{g['keyframes'] - g['held_keyframes']} of {g['keyframes']} in {g['solve_s']:.2f} s"
                              for g in windowed)
            print(f"GBA of what a merge changed (free of the solve's keyframes, the rest held): {parts}")
        budgeted = [g for g in gba if g.get("budget_reached")]
        section["gba_budget_reached"] = len(budgeted)
        if budgeted:
            # How far from converged each stopped: its last accepted step's relative decrease of the cost.
            last_steps = []
            for g in budgeted:
                steps = [c for _, c in g.get("accepted_steps", [])]
                if len(steps) >= 2 and steps[-1] > 0:
                    last_steps.append(100.0 * (steps[-2] - steps[-1]) / steps[-1])
            tail = (f"; their last step lowered the cost by {min(last_steps):.2f}-{max(last_steps):.2f} %"
                    if last_steps else "")
            print(f"GBA stopped at its time budget (applied; the map's next GBA goes on): {len(budgeted)} of "
                  f"{len(gba)}{tail}")
        changes = backend.get("merges", []) + backend.get("loops", [])
        corrected = [c["match_to_corrected_s"] for c in changes if c.get("match_to_corrected_s", -1) >= 0]
        refined = [c["match_to_optimised_s"] for c in changes if c.get("match_to_optimised_s", -1) >= 0]
        section["match_to_corrected_s"] = corrected
        section["match_to_refined_s"] = refined
        print(f"match or loop -> map corrected (the merge's rigid correction, or the loop's pose graph): "
              f"{spread(corrected)}")
        print(f"match or loop -> map refined by the GBA after it: {spread(refined)}")
        loops = loops_against_truth(mission, backend.get("loops", []))
        if loops:
            section["loops_against_truth"] = loops
            print("loops against the ground truth (the query keyframe's pose in the candidate's): error of what place "
                  "recognition measured / of what the map held before the pose graph [cm, deg]: " +
                  ", ".join(f"{r['measured_cm']:.1f}/{r['map_cm']:.1f} cm {r['measured_deg']:.2f}/{r['map_deg']:.2f} deg"
                            for r in loops))
        print(f"new keyframes fused with their covisible and nearby keyframes: {section['new_keyframes_fused']} "
              f"({section['new_keyframe_links']} keypoints linked, {section['new_keyframe_point_merges']} points "
              f"merged; {section['new_keyframe_fuse_ms_mean']:.1f} ms mean, "
              f"{section['new_keyframe_fuse_ms_max']:.1f} ms max per keyframe, of which under the map's locks at most "
              f"{section['new_keyframe_fuse_locked_ms_max']:.1f} ms)")
    else:
        print("no backend.json (the server ran with --no-backend)")
    print("ingest per batch, arrival to stored with map-lock waits included [ms]: all batches, and those that met "
          "a running GBA")
    print(f"{'agent':8} {'batches':>8} {'p50':>7} {'p99':>7} {'max':>7}   {'with GBA':>8} {'p50':>7} {'p99':>7} "
          f"{'max':>7}")
    ingest = {}

    def latency(i):
        return {"batches": int(i.get("samples", 0)), "p50_ms": i.get("p50", 0.0), "p99_ms": i.get("p99", 0.0),
                "max_ms": i.get("max", 0.0)}

    for (m, agent), a in sorted(server_agents.items()):
        if m != name or "ingest_ms" not in a:
            continue
        r = latency(a["ingest_ms"])
        g = latency(a.get("ingest_during_gba_ms", {}))
        ingest[f"agent{agent}"] = dict(r, during_gba=g)
        print(f"{'agent' + str(agent):8} {r['batches']:8d} {r['p50_ms']:7.2f} {r['p99_ms']:7.2f} {r['max_ms']:7.2f}   "
              f"{g['batches']:8d} {g['p50_ms']:7.2f} {g['p99_ms']:7.2f} {g['max_ms']:7.2f}")
    section["ingest"] = ingest
    pooled = pooled_ingest(os.path.join(out, "server", "ingest_ms.csv"), name)
    if pooled is not None:
        section["ingest_pooled"] = pooled
        tail = pooled["slowest_1pct"]
        print(f"all agents pooled: {pooled['batches']} batches, p50 {pooled['p50_ms']:.2f} ms, p99 "
              f"{pooled['p99_ms']:.2f} ms; the slowest 1 % ({tail['batches']}) spent on average "
              f"{tail['record_wait_ms']:.1f} ms waiting for the agent record's lock, {tail['map_wait_ms']:.1f} ms "
              f"for the maps' locks, {tail['cpu_ms']:.1f} ms on a core and "
              f"{tail['off_core_ms']:.1f} ms ready but off a core")
    summary["backend"] = section


def loops_against_truth(mission, loops):
    """Each closed loop's relative pose (query keyframe in the candidate's frame) as measured and as the map held it,
    against the truth at the two keyframes' times: tells a wrong loop measurement from a map that was off."""
    truth = {}
    rows = []
    for loop in loops:
        if "T_cs_qs_measured" not in loop:
            return []
        poses = []
        for (agent, _), t_ns in ((loop["query"], loop["query_t_ns"]), (loop["candidate"], loop["candidate_t_ns"])):
            if agent not in truth:
                truth[agent] = read_groundtruth(os.path.join(mission["dataset"], f"agent{agent}")) or []
            poses.append(nearest_truth(truth[agent], t_ns))
        if None in poses:
            continue
        (q_q, p_q), (q_c, p_c) = poses
        true = pose_mul(pose_inv((q_c, p_c)), (q_q, p_q))
        row = {"query": loop["query"], "candidate": loop["candidate"]}
        for key, name in (("T_cs_qs_measured", "measured"), ("T_cs_qs_map", "map")):
            x, y, z, qx, qy, qz, qw = loop[key]
            row[f"{name}_cm"] = 100.0 * math.dist(true[1], (x, y, z))
            row[f"{name}_deg"] = angle_between_deg(true[0], (qw, qx, qy, qz))
        rows.append(row)
    return rows


def nearest_truth(rows, t_ns, tolerance_ns=5_000_000):
    """The ground-truth pose (quaternion w-first, position) nearest t_ns, within the tolerance; None otherwise."""
    i = bisect.bisect_left(rows, (t_ns,))
    best = min((rows[j] for j in (i - 1, i) if 0 <= j < len(rows)), key=lambda r: abs(r[0] - t_ns), default=None)
    if best is None or abs(best[0] - t_ns) > tolerance_ns:
        return None
    return best[2], best[1]


def pooled_ingest(path, mission_name):
    """Every batch of the mission's agents pooled (ingest_ms.csv), and where the slowest 1 % spent their time."""
    if not os.path.exists(path):
        return None
    with open(path) as f:
        rows = [r for r in csv.DictReader(f) if r["mission"] == mission_name]
    if not rows or "cpu_ms" not in rows[0]:
        return None
    rows.sort(key=lambda r: float(r["ingest_ms"]))
    ms = [float(r["ingest_ms"]) for r in rows]
    slow = rows[-max(1, len(rows) // 100):]

    def mean(key):
        return sum(float(r[key]) for r in slow) / len(slow)

    record_wait, map_wait, cpu, total = mean("record_wait_ms"), mean("map_wait_ms"), mean("cpu_ms"), mean("ingest_ms")
    return {"batches": len(rows), "p50_ms": nearest_rank(ms, 0.5), "p99_ms": nearest_rank(ms, 0.99),
            "slowest_1pct": {"batches": len(slow), "ingest_ms": total, "record_wait_ms": record_wait,
                             "map_wait_ms": map_wait, "cpu_ms": cpu,
                             "off_core_ms": max(0.0, total - record_wait - map_wait - cpu)}}


def report_recognition(out, mission, map_to_truth, summary):
    """The server's place recognition: counters, and each accepted map match against the ground truth (each agent's
    single server map aligned to the ground truth in SE3 gives the true transform between two maps)."""
    rows = []
    for name in [mission.get("mission", mission["preset"])]:
        rec = load_json(os.path.join(out, "server", name, "recognition.json"))
        if rec is None:
            continue
        errors_t, errors_r, wrong, scored = [], [], 0, 0
        for m in rec.get("matches", []):
            if m["kind"] != "map_match":
                continue
            # The maps' frames are those of the agents they were opened for (a merged map keeps its frame);
            # outputs older than the origins fall back to the matched keyframes' agents.
            qa = (name, m["query_map_origin"][0] if "query_map_origin" in m else m["query"][0])
            ca = (name, m["candidate_map_origin"][0] if "candidate_map_origin" in m else m["candidate"][0])
            if qa not in map_to_truth or ca not in map_to_truth:
                continue
            T_gt_q, T_gt_c = (eval_transform(map_to_truth[m])[:2] for m in (qa, ca))  # SE3: scale 1
            true = pose_mul(pose_inv(T_gt_q), T_gt_c)
            x, y, z, qx, qy, qz, qw = m["T_qmap_cmap"]
            est = ((qw, qx, qy, qz), (x, y, z))
            p = tuple(m["p_cmap_query"])
            dt = math.dist(pose_apply(true, p), pose_apply(est, p))
            dr = angle_between_deg(true[0], est[0])
            scored += 1
            errors_t.append(dt)
            errors_r.append(dr)
            wrong += 1 if (dt > 0.5 or dr > 5.0) else 0
        errors_t.sort()
        errors_r.sort()
        row = {"mission": name, "keyframes": rec["keyframes"], "queries": rec["queries"],
               "candidates": rec["candidates"], "loops": rec["loops"], "map_matches": rec["map_matches"],
               "busy_s": rec["busy_s"],
               "query_ms_p99": rec.get("query_ms", {}).get("p99"),
               "lock_held_ms_p99": rec.get("lock_held_ms", {}).get("p99"),
               "lock_held_ms_max": rec.get("lock_held_ms", {}).get("max"),
               "map_matches_scored": scored, "map_matches_wrong": wrong,
               "translation_error_p50_m": errors_t[len(errors_t) // 2] if errors_t else None,
               "translation_error_max_m": errors_t[-1] if errors_t else None,
               "rotation_error_p50_deg": errors_r[len(errors_r) // 2] if errors_r else None,
               "rotation_error_max_deg": errors_r[-1] if errors_r else None}
        rows.append(row)
    if not rows:
        return
    summary["recognition"] = rows
    print()
    print("== place recognition on the server, on the agents' own maps (loops: inside a map; map matches: across "
          "maps; the back-end merges maps on map matches and closes loops: see backend.json)")
    print(f"{'mission':10} {'KFs':>5} {'queries':>8} {'verified':>9} {'loops':>6} {'matches':>8} {'busy[s]':>8}  "
          "map matches against ground truth: wrong (>0.5 m or 5 deg), error p50 / max")
    for r in rows:
        errs = (f"{r['map_matches_wrong']} of {r['map_matches_scored']} wrong, "
                f"{cm(r['translation_error_p50_m'])} / {cm(r['translation_error_max_m'])} cm, "
                f"{r['rotation_error_p50_deg']:.2f} / {r['rotation_error_max_deg']:.2f} deg"
                if r["map_matches_scored"] else "none scored")
        print(f"{r['mission']:10} {r['keyframes']:5d} {r['queries']:8d} {r['candidates']:9d} {r['loops']:6d} "
              f"{r['map_matches']:8d} {r['busy_s']:8.1f} {ms(r['query_ms_p99']):>9} "
              f"{ms(r['lock_held_ms_p99']) + ' / ' + ms(r['lock_held_ms_max']):>17}  {errs}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="the mission's output folder")
    parser.add_argument("--eval", required=True, help="the cvislam_eval executable")
    args = parser.parse_args()
    out = args.out
    mission = load_json(os.path.join(out, "mission.json"))
    if mission is None:
        sys.exit(f"mission_report: {out}/mission.json is missing or unreadable: run deploy/run_mission.sh first")
    eval_dir = os.path.join(out, "eval")
    os.makedirs(eval_dir, exist_ok=True)
    server_stats = load_json(os.path.join(out, "server", "stats.json")) or {"agents": [], "maps": []}
    server_agents = {(a["mission"], int(a["agent_id"])): a for a in server_stats.get("agents", [])}
    name = mission["mission"]

    summary = {"mission": mission, "agents": [], "joint": None, "traffic": [], "messages": {}, "stages": {},
               "real_data": None}

    # Accuracy, per agent: onboard (every tracked frame) and the server's keyframes of it.
    print()
    print(f"== accuracy: {name}, {mission['mode']}-inertial, simulated (preset {mission['preset']}, seed "
          f"{mission['seed']}, {mission['duration_s']} s); ATE after SE3 alignment, scale error from Sim3")
    print("onboard: every tracked frame after the IMU initialisation, hung from its keyframe's final pose "
          "(trajectory.txt); live: the pose tracking gave at the frame's time (trajectory_online.txt)")
    print(f"{'agent':8} {'frames':>6} {'onboard ATE[cm]':>16} {'live ATE[cm]':>13} {'scale err%':>10} "
          f"{'server KFs':>10} {'server ATE[cm]':>15} {'scale err%':>10} {'maps':>5}")
    pairs_server = []
    map_to_truth = {}
    for a in mission["agents"]:
        agent_id = int(a.replace("agent", ""))
        gt = os.path.join(mission["dataset"], a)
        onboard = run_eval(args.eval, [(os.path.join(out, "agents", a, "trajectory.txt"), gt)],
                           os.path.join(eval_dir, f"onboard_{a}.json"), per_pose=True)
        live_file = os.path.join(out, "agents", a, "trajectory_online.txt")
        live = run_eval(args.eval, [(live_file, gt)], os.path.join(eval_dir, f"live_{a}.json")) \
            if os.path.exists(live_file) else None
        server_file = os.path.join(out, "server", name, f"keyframes_agent{agent_id}.txt")
        # An agent whose tracking restarted has one server map per agent map, each in its own frame until map
        # fusion: score each map on its own and pool them.
        server_dir = os.path.join(out, "server", name)
        per_map = sorted(os.path.join(server_dir, f) for f in (os.listdir(server_dir) if os.path.isdir(server_dir)
                                                                else [])
                         if f.startswith(f"keyframes_agent{agent_id}_map"))
        server = None
        if per_map:
            pairs = [(f, gt) for f in per_map]
            pooled = run_eval(args.eval, pairs, os.path.join(eval_dir, f"server_{a}.json"), align="each")
            if pooled is not None:
                server = dict(pooled["joint"])
                server["poses"] = pooled["joint"]["poses"]
            pairs_server.extend(pairs)
        elif os.path.exists(server_file):
            server = run_eval(args.eval, [(server_file, gt)], os.path.join(eval_dir, f"server_{a}.json"),
                              per_pose=True)
            pairs_server.append((server_file, gt))
        # The agent's own world frame is its server map's frame until a merge moves it: matches are scored
        # against the onboard trajectory's alignment, which stays that of the frame the match was made in.
        if onboard is not None and "transform_gt_est" in onboard.get("se3", {}):
            map_to_truth[(name, agent_id)] = onboard["se3"]["transform_gt_est"]
        s = server_agents.get((name, agent_id), {})
        row = {"agent": a, "frames": onboard["poses"] if onboard else 0,
               "onboard_ate_se3_m": ate(onboard), "onboard_ate_sim3_m": ate(onboard, "sim3"),
               "live_ate_se3_m": ate(live),
               "onboard_scale_error_percent": onboard["scale_error_percent"] if onboard else None,
               "server_keyframes": int(s.get("server_keyframes", s.get("keyframes", 0))),
               "server_ate_se3_m": ate(server), "server_ate_sim3_m": ate(server, "sim3"),
               "server_scale_error_percent": server.get("scale_error_percent") if server else None,
               "server_maps": int(s.get("maps", 0))}
        summary["agents"].append(row)
        scale_on = row["onboard_scale_error_percent"]
        scale_sv = row["server_scale_error_percent"]
        print(f"{a:8} {row['frames']:6d} {cm(row['onboard_ate_se3_m']):>16} {cm(row['live_ate_se3_m']):>13} "
              f"{(f'{scale_on:+.2f}' if scale_on is not None else 'n/a'):>10} {row['server_keyframes']:10d} "
              f"{cm(row['server_ate_se3_m']):>15} {(f'{scale_sv:+.2f}' if scale_sv is not None else 'n/a'):>10} "
              f"{row['server_maps']:5d}")
        if row["server_maps"] > 1:
            print(f"{'':8} tracking restarted: {row['server_maps']} maps; the server figure pools the maps, each aligned "
                  f"on its own; the onboard figure aligns the whole trajectory at once")

    # Joint: every agent's server keyframes against the ground truth. When the back-end fused every agent into one
    # map, one transform aligns them all; otherwise each map is aligned on its own and the errors are pooled.
    mission_maps = [m for m in server_stats.get("maps", []) if m.get("mission") == name and int(m.get("keyframes", 0)) > 0]
    fused = len(mission_maps) == 1 and len(mission_maps[0].get("agents", [])) == len(mission["agents"])
    if pairs_server:
        joint = run_eval(args.eval, pairs_server, os.path.join(eval_dir, "joint_server.json"),
                         align="joint" if fused else "each")
        if joint is not None and "joint" in joint:
            j = joint["joint"]
            summary["joint"] = {"align": joint.get("align", "each"), "poses": j.get("poses"),
                                "ate_se3_m": j["se3"]["rmse"], "ate_sim3_m": j["sim3"]["rmse"]}
        else:
            # cvislam_eval without joint scoring: pool the per-agent SE3 errors by hand.
            n = sum(r["server_keyframes"] for r in summary["agents"] if not math.isnan(r["server_ate_se3_m"]))
            sq = sum(r["server_keyframes"] * r["server_ate_se3_m"] ** 2 for r in summary["agents"]
                     if not math.isnan(r["server_ate_se3_m"]))
            summary["joint"] = {"align": "each", "poses": n, "ate_se3_m": math.sqrt(sq / n) if n else None,
                                "ate_sim3_m": None}
        jt = summary["joint"]
        print(f"{'joint':8} {'':6} {'':>16} {'':>13} {'':>10} {jt['poses'] or 0:10d} {cm(jt['ate_se3_m']):>15}   "
              + ("(server keyframes of all agents in one fused map, aligned with one transform)" if fused else
                 f"(server keyframes of all agents; {len(mission_maps)} server maps, each aligned on its own)"))

    # Traffic per agent and direction (paper, Table IV: 0.12-0.15 MB/s up, about 0.7 MB/s down).
    print()
    print("== traffic per agent, agent side, per second of sensor time (paper Table IV: up 0.12-0.15 MB/s, "
          "down about 0.7)")
    print(f"{'agent':8} {'sensor[s]':>9} {'up[MB]':>8} {'up[MB/s]':>9} {'down[MB]':>9} {'down[MB/s]':>10} "
          f"{'batches':>8} {'reconnects':>10} {'unacked KFs':>11}")
    kinds_up = {}
    kinds_down = {}
    for a in mission["agents"]:
        link = load_json(os.path.join(out, "agents", a, "link.json"))
        if link is None:
            continue
        up_msgs, up_bytes = counter(link["up"], "message")
        down_msgs, down_bytes = counter(link["down"], "message")
        batches, _ = counter(link["up"], "batch")
        # Rates per second of the sequence's own time, so that they do not depend on the playback pace.
        duration = max(float(mission["duration_s"]), 1e-9)
        row = {"agent": a, "sensor_s": duration, "wall_s": link["duration_s"], "up_bytes": up_bytes,
               "down_bytes": down_bytes,
               "up_mb_per_s": up_bytes / 1e6 / duration, "down_mb_per_s": down_bytes / 1e6 / duration,
               "batches": batches, "reconnects": max(0, int(link["connections"]) - 1),
               "keyframes_unacknowledged": int(link["keyframes_unacknowledged"]),
               "covisible_maps_accepted": int(link.get("covisible_maps_accepted", 0)),
               "covisible_maps_refused": int(link.get("covisible_maps_refused", 0))}
        summary["traffic"].append(row)
        print(f"{a:8} {duration:9.1f} {up_bytes / 1e6:8.2f} {row['up_mb_per_s']:9.3f} {down_bytes / 1e6:9.4f} "
              f"{row['down_mb_per_s']:10.4f} {batches:8d} {row['reconnects']:10d} {row['keyframes_unacknowledged']:11d}")
        for direction, kinds in (("up", kinds_up), ("down", kinds_down)):
            for kind, c in link[direction].items():
                k = kinds.setdefault(kind, [0, 0])
                k[0] += int(c["messages"])
                k[1] += int(c["bytes"])

    if summary["traffic"]:
        accepted = ", ".join(f"{r['agent']} {r['covisible_maps_accepted']}" for r in summary["traffic"])
        refused = sum(r["covisible_maps_refused"] for r in summary["traffic"])
        print(f"covisible maps from the server, checked and accepted: {accepted}; refused: {refused}")
        report_downlink_use(out, mission, summary)
    print()
    print("== messages by kind, all agents (up: what the server counted as received; sizes are serialized bytes)")
    print(f"{'direction':9} {'kind':16} {'count':>9} {'bytes':>12} {'bytes each':>11}")
    server_up = {}
    server_down = {}
    for (m, _agent), s in server_agents.items():
        if m != name:
            continue
        for direction, kinds in (("up", server_up), ("down", server_down)):
            for kind, c in s.get(direction, {}).items():
                k = kinds.setdefault(kind, [0, 0])
                k[0] += int(c["messages"])
                k[1] += int(c["bytes"])
    order_up = ["message", "hello", "batch", "keyframe", "point", "observation", "keyframe_update", "point_update",
                "merge", "removal", "goodbye"]
    order_down = ["message", "welcome", "ack", "correction"]
    for direction, kinds, order in (("up", server_up, order_up), ("down", server_down, order_down)):
        for kind in order + sorted(set(kinds) - set(order)):
            if kind not in kinds:
                continue
            n, b = kinds[kind]
            each = f"{b / n:11.1f}" if n and b else f"{'':>11}"
            print(f"{direction:9} {kind:16} {n:9d} {b:12d} {each}")
            summary["messages"].setdefault(direction, {})[kind] = {"count": n, "bytes": b,
                                                                  "bytes_each": (b / n) if n else None}
    summary["messages"]["agent_side"] = {"up": kinds_up, "down": kinds_down}

    # The agents' stage timings with the link on (paper Fig. 4).
    print()
    print("== agent stage timings with the link on, p50 / p99 [ms] (this 2-core machine, all agents and the "
          "server sharing it)")
    stages = ["orb_extraction", "matching", "pose_optimisation", "motion_ba", "tracking_total", "local_ba",
              "mapping_total"]
    print(f"{'agent':8} " + " ".join(f"{s[:15]:>15}" for s in stages))
    for a in mission["agents"]:
        lat = load_json(os.path.join(out, "agents", a, "latency.json"))
        if lat is None:
            continue
        summary["stages"][a] = {s: {"p50_ms": lat[s]["p50_ms"], "p99_ms": lat[s]["p99_ms"]} for s in stages
                                if s in lat}
        cells = []
        for s in stages:
            cells.append(f"{lat[s]['p50_ms']:6.1f} / {lat[s]['p99_ms']:5.1f}" if s in lat else f"{'n/a':>15}")
        print(f"{a:8} " + " ".join(f"{c:>15}" for c in cells))

    report_recognition(out, mission, map_to_truth, summary)
    report_backend(out, mission, server_agents, summary)

    # Real images: the V1_01 excerpt through the same server.
    real_out = os.path.join(out, "agents", "real_v101")
    if os.path.isdir(real_out) and os.path.isdir(mission.get("real_data", "")):
        onboard = run_eval(args.eval, [(os.path.join(real_out, "trajectory.txt"), mission["real_data"])],
                           os.path.join(eval_dir, "onboard_real_v101.json"))
        live_file = os.path.join(real_out, "trajectory_online.txt")
        live = run_eval(args.eval, [(live_file, mission["real_data"])],
                        os.path.join(eval_dir, "live_real_v101.json")) if os.path.exists(live_file) else None
        server_file = os.path.join(out, "server", "euroc-v101", "keyframes_agent0.txt")
        server = run_eval(args.eval, [(server_file, mission["real_data"])],
                          os.path.join(eval_dir, "server_real_v101.json")) if os.path.exists(server_file) else None
        s = server_agents.get(("euroc-v101", 0), {})
        summary["real_data"] = {"frames": onboard["poses"] if onboard else 0, "onboard_ate_se3_m": ate(onboard),
                                "live_ate_se3_m": ate(live),
                                "server_keyframes": int(s.get("keyframes", 0)), "server_ate_se3_m": ate(server),
                                "up_bytes": counter(s.get("up", {}), "message")[1]}
        r = summary["real_data"]
        print()
        print("== real data: EuRoC V1_01 excerpt (4.7 s, stereo-inertial), one agent through the server")
        print(f"onboard ATE {r['onboard_ate_se3_m'] * 1000:.1f} mm (live {r['live_ate_se3_m'] * 1000:.1f} mm) over "
              f"{r['frames']} frames; server holds "
              f"{r['server_keyframes']} keyframes, ATE {r['server_ate_se3_m'] * 1000:.1f} mm; "
              f"{r['up_bytes'] / 1e6:.2f} MB up")

    for row in summary["agents"]:
        for k, v in list(row.items()):
            if isinstance(v, float) and math.isnan(v):
                row[k] = None
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    mission_pictures.write_report(out, summary)


if __name__ == "__main__":
    main()
