#!/usr/bin/env python3
"""The agent's accuracy as a distribution over simulator seeds, not a row: renders N seeds of each preset once into
a cache (in parallel), runs every agent of every mission alone in each mode (--pace sync, so a run is reproducible),
pinned one run per core, scores each with cvislam_eval, and reports per preset and mode the median, p90 and max
of the SE3 ATE of the refined and of the live trajectory, the refined trajectory's ATE after a Sim3 alignment
(what is left once its one scale error is taken out), the scale error, the tracked fraction, the maps and the
IMU initialisation time (from the first image, and from the first motion in the ground truth). With --b-config or
--b-build every run is made twice (A and B) and the report adds the paired ratios B/A per run: geometric mean,
worst, and how many got worse by more than 10 %.

  test/bench/agent_accuracy_seeds.py [--build build/default] [--presets loop,aggressive,euroc-mh] [--seeds 100-119]
      [--modes mono,stereo] [--jobs 2] [--config A.yaml] [--b-build DIR] [--b-config B.yaml] [--out DIR]
      [--plots N]

Every figure here is SIMULATED. Results stay in --out (default $CVISLAM_SIM_CACHE/seeds, with the renders beside
it): a run whose eval.json is there already is not made again, so an interrupted sweep resumes. The report goes to
stdout (markdown) and, with every run's figures, to OUT/report.json. With --plots N it then draws the error over
time of the N worst runs of each preset and mode (tools/error_over_time.py: position error, and the heading and scale
in 5 s windows) into OUT/plots/ and sums up each in one line.
"""
import argparse
import csv
import functools
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def parse_seeds(text):
    seeds = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        try:
            a, b = int(first), int(last or first)
        except ValueError:
            sys.exit(f"agent_accuracy_seeds: --seeds {text!r}: expected numbers and ranges like 100-119,130")
        if b < a:
            sys.exit(f"agent_accuracy_seeds: --seeds {text!r}: the range {part} runs backwards")
        seeds.extend(range(a, b + 1))
    return seeds


def quantile(values, q):
    """Linear interpolation between order statistics (numpy's default)."""
    s = sorted(values)
    if not s:
        return float("nan")
    pos = q * (len(s) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


# A body slower than this is at rest: EuRoC's ground truth of a drone on the floor moves under 0.02 m/s.
FIRST_MOTION_SPEED_M_S = 0.1


@functools.lru_cache(maxsize=None)
def first_motion_s(agent_dir):
    """Seconds from the first image to the first ground-truth speed of FIRST_MOTION_SPEED_M_S. An IMU initialisation
    needs motion, so its time is also counted from here: the replayed MH_05 of euroc-mh stands still for 2.5 s."""
    mav = Path(agent_dir) / "mav0"
    with open(mav / "cam0" / "data.csv") as f:
        first_image_ns = next(int(row[0]) for row in csv.reader(f) if row and not row[0].startswith("#"))
    with open(mav / "state_groundtruth_estimate0" / "data.csv") as f:
        for row in csv.reader(f):
            if not row or row[0].startswith("#"):
                continue
            if math.hypot(float(row[8]), float(row[9]), float(row[10])) >= FIRST_MOTION_SPEED_M_S:
                return max(0.0, (int(row[0]) - first_image_ns) * 1e-9)
    return 0.0


class Sweep:
    def __init__(self, args):
        self.args = args
        cache = Path(os.environ.get("CVISLAM_SIM_CACHE", REPO / "out" / "sim-cache"))
        self.renders = cache / "seeds"
        self.out = Path(args.out) if args.out else cache / "seeds" / "runs"
        self.variants = {"A": (Path(args.build), args.config)}
        if args.b_build or args.b_config:
            self.variants["B"] = (Path(args.b_build or args.build), args.b_config or args.config)
        self.slots = list(range(args.jobs))
        self.free_slots = list(self.slots)
        self.lock = threading.Lock()
        self.done = 0
        self.total = 0
        self.started = time.monotonic()

    # --- rendering --------------------------------------------------------------------------------------------
    def mission_dir(self, preset, seed):
        return self.renders / f"{preset}-seed{seed}-{self.args.duration:g}s"

    def render(self, preset, seed):
        folder = self.mission_dir(preset, seed)
        # Written only once the simulator has finished: an interrupted render is made again.
        done = folder / ".rendered"
        if done.exists():
            return folder
        sim = Path(self.args.build) / "bin" / "cvislam_sim"
        log = folder.with_suffix(".log")
        folder.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "w") as f:
            rc = subprocess.call([str(sim), "--preset", preset, "--seed", str(seed), "--duration",
                                  str(self.args.duration), "--stereo", "--threads", "1", "--overwrite", "--quiet",
                                  "--out", str(folder)], stdout=f, stderr=subprocess.STDOUT)
        if rc != 0 or not (folder / "mission.yaml").exists():
            sys.exit(f"agent_accuracy_seeds: rendering {preset} seed {seed} failed ({rc}): see {log}")
        done.touch()
        return folder

    # --- one run ----------------------------------------------------------------------------------------------
    def take_slot(self):
        while True:
            with self.lock:
                if self.free_slots:
                    return self.free_slots.pop(0)
            time.sleep(0.05)

    def run(self, job):
        variant, preset, seed, agent_dir, mode = job
        build, config = self.variants[variant]
        out = self.out / variant / f"{preset}-seed{seed}-{agent_dir.name}-{mode}"
        result = out / "result.json"
        if not result.exists():
            slot = self.take_slot()
            try:
                self.run_agent(build, config, agent_dir, mode, out, slot)
            finally:
                with self.lock:
                    self.free_slots.append(slot)
        with self.lock:
            self.done += 1
            elapsed = time.monotonic() - self.started
            print(f"[{self.done}/{self.total}] {variant} {preset} seed {seed} {agent_dir.name} {mode} "
                  f"({elapsed:.0f} s)", file=sys.stderr, flush=True)
        record = json.loads(result.read_text())
        add_sim3_to_older_record(record, out)
        record.update(variant=variant, preset=preset, seed=seed, agent=agent_dir.name, mode=mode,
                      first_motion_s=first_motion_s(str(agent_dir)))
        return record

    def run_agent(self, build, config, agent_dir, mode, out, slot):
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        # Runs share one RouDi, so each concurrent run needs its own agent id (the ids name its topics).
        args = ["taskset", "-c", str(slot % os.cpu_count()), str(build / "bin" / "cvislam_agent"), "--dataset",
                str(agent_dir), "--output", str(out / "agent"), "--mode", mode, "--pace", "sync", "--quiet",
                "--roudi", "external", "--agent-id", str(slot)]
        if config:
            args += ["--config", config]
        with open(out / "agent.log", "w") as log:
            rc = subprocess.call(args, stdout=log, stderr=subprocess.STDOUT)
        record = {"failed": rc != 0}
        if rc == 0:
            summary = json.loads((out / "agent" / "summary.json").read_text())
            record.update(frames=summary["frames"], tracked=summary["tracked_frames"],
                          maps=summary.get("new_maps", 1), imu_init_s=summary.get("imu_initialised_at_s", -1.0))
            for name in ("trajectory", "trajectory_online"):
                scored = self.score(build, out / "agent" / f"{name}.txt", agent_dir, out / f"eval_{name}.json")
                if scored is None:
                    record["failed"] = True
                    break
                record[name] = scored
        (out / "result.json").write_text(json.dumps(record, indent=1))

    @staticmethod
    def score(build, estimate, groundtruth, json_out):
        rc = subprocess.call([str(build / "bin" / "cvislam_eval"), "--estimate", str(estimate), "--groundtruth",
                              str(groundtruth), "--json", str(json_out), "--quiet"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if rc != 0:
            return None
        e = json.loads(json_out.read_text())
        return {"ate_se3_m": e["se3"]["rmse"], "ate_sim3_m": e.get("sim3", {}).get("rmse"),
                "scale_error_percent": e.get("scale_error_percent", 0.0),
                "poses_left_out_before_init": e.get("before_initialisation", 0)}

    # --- the sweep --------------------------------------------------------------------------------------------
    def missions(self):
        wanted = [(p, s) for p in self.args.presets for s in self.args.seeds]
        with ThreadPoolExecutor(max_workers=self.args.jobs) as pool:
            folders = list(pool.map(lambda ps: self.render(*ps), wanted))
        return [(p, s, f) for (p, s), f in zip(wanted, folders)]

    def jobs(self, missions):
        jobs = []
        for preset, seed, folder in missions:
            for agent_dir in sorted(folder.glob("agent*")):
                for mode in self.args.modes:
                    for variant in self.variants:
                        jobs.append((variant, preset, seed, agent_dir, mode))
        return jobs

    def sweep(self):
        missions = self.missions()
        jobs = self.jobs(missions)
        self.total = len(jobs)
        with ThreadPoolExecutor(max_workers=self.args.jobs) as pool:
            return list(pool.map(self.run, jobs))


def add_sim3_to_older_record(record, out):
    """A run made before the Sim3 ATE was recorded: taken from its eval file when that holds it."""
    for name in ("trajectory", "trajectory_online"):
        scored, eval_json = record.get(name), out / f"eval_{name}.json"
        if scored is not None and "ate_sim3_m" not in scored and eval_json.exists():
            scored["ate_sim3_m"] = json.loads(eval_json.read_text()).get("sim3", {}).get("rmse")


def distribution_rows(records, variant):
    rows = []
    keys = sorted({(r["preset"], r["mode"]) for r in records if r["variant"] == variant})
    for preset, mode in keys:
        rs = [r for r in records if r["variant"] == variant and r["preset"] == preset and r["mode"] == mode]
        ok = [r for r in rs if not r["failed"]]
        row = {"variant": variant, "preset": preset, "mode": mode, "runs": len(rs), "failed": len(rs) - len(ok)}
        if ok:
            for name in ("trajectory", "trajectory_online"):
                ates = [100.0 * r[name]["ate_se3_m"] for r in ok]
                row[name] = {"median_cm": statistics.median(ates), "p90_cm": quantile(ates, 0.9),
                             "max_cm": max(ates)}
            sim3 = [100.0 * r["trajectory"]["ate_sim3_m"] for r in ok
                    if r["trajectory"].get("ate_sim3_m") is not None]
            row["trajectory_sim3"] = {"median_cm": statistics.median(sim3), "max_cm": max(sim3)} if sim3 else None
            row["scale_error_abs_median_percent"] = statistics.median(
                abs(r["trajectory"]["scale_error_percent"]) for r in ok)
            row["scale_error_abs_max_percent"] = max(abs(r["trajectory"]["scale_error_percent"]) for r in ok)
            row["tracked_fraction_min"] = min(r["tracked"] / r["frames"] for r in ok)
            row["runs_with_several_maps"] = sum(1 for r in ok if r["maps"] > 1)
            inits = [r["imu_init_s"] for r in ok if r["imu_init_s"] >= 0]
            row["imu_init_median_s"] = statistics.median(inits) if inits else None
            row["imu_init_max_s"] = max(inits) if inits else None
            after_motion = [r["imu_init_s"] - r["first_motion_s"] for r in ok if r["imu_init_s"] >= 0]
            row["imu_init_after_motion_median_s"] = statistics.median(after_motion) if after_motion else None
            row["imu_init_after_motion_max_s"] = max(after_motion) if after_motion else None
            row["imu_never_initialised"] = sum(1 for r in ok if r["imu_init_s"] < 0)
            worst = max(ok, key=lambda r: r["trajectory"]["ate_se3_m"])
            row["worst_run"] = f"seed {worst['seed']} {worst['agent']}"
        rows.append(row)
    return rows


def paired_rows(records):
    by_key = {}
    for r in records:
        if r["failed"]:
            continue
        by_key.setdefault((r["preset"], r["mode"], r["seed"], r["agent"]), {})[r["variant"]] = r
    rows = []
    for preset, mode in sorted({(k[0], k[1]) for k in by_key}):
        pairs = [v for k, v in by_key.items() if k[0] == preset and k[1] == mode and "A" in v and "B" in v]
        if not pairs:
            continue
        row = {"preset": preset, "mode": mode, "pairs": len(pairs)}
        for name in ("trajectory", "trajectory_online"):
            ratios = [(p["B"][name]["ate_se3_m"] / p["A"][name]["ate_se3_m"], p["A"]) for p in pairs
                      if p["A"][name]["ate_se3_m"] > 0]
            worst_ratio, worst_a = max(ratios, key=lambda x: x[0])
            row[name] = {"geomean": math.exp(statistics.fmean(math.log(x) for x, _ in ratios)),
                         "best": min(x for x, _ in ratios), "worst": worst_ratio,
                         "worst_run": f"seed {worst_a['seed']} {worst_a['agent']}",
                         "worse_by_10_percent": sum(1 for x, _ in ratios if x > 1.1),
                         "better_by_10_percent": sum(1 for x, _ in ratios if x < 1 / 1.1)}
        rows.append(row)
    return rows


def print_report(args, sweep, distribution, paired):
    print(f"SIMULATED: presets {', '.join(args.presets)}; seeds {args.seeds[0]}-{args.seeds[-1]} "
          f"({len(args.seeds)}); {args.duration:g} s per agent; --pace sync; per-frame ATE after SE3 alignment "
          f"(refined: trajectory.txt; live: trajectory_online.txt)")
    for variant, (build, config) in sweep.variants.items():
        print(f"  {variant}: {build}" + (f" with --config {config}" if config else ""))
    print()
    print("| variant | preset | mode | runs | ATE refined median / p90 / max [cm] | ATE live median / p90 / max [cm] |"
          " ATE refined after Sim3 median / max [cm] | scale err median / max [%] | tracked min | >1 map |"
          " IMU init median / max [s]: from the first image; from the first motion | worst run |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in distribution:
        if "trajectory" not in r:
            print(f"| {r['variant']} | {r['preset']} | {r['mode']} | {r['runs']} | all failed | | | | | | | |")
            continue
        t, o, t3 = r["trajectory"], r["trajectory_online"], r["trajectory_sim3"]
        sim3 = "n/a" if t3 is None else f"{t3['median_cm']:.2f} / {t3['max_cm']:.2f}"
        init = "never" if r["imu_init_median_s"] is None else (
            f"{r['imu_init_median_s']:.2f} / {r['imu_init_max_s']:.2f}; "
            f"{r['imu_init_after_motion_median_s']:.2f} / {r['imu_init_after_motion_max_s']:.2f}")
        if r["imu_never_initialised"]:
            init += f" ({r['imu_never_initialised']} never)"
        failed = f" ({r['failed']} failed)" if r["failed"] else ""
        print(f"| {r['variant']} | {r['preset']} | {r['mode']} | {r['runs']}{failed} | "
              f"{t['median_cm']:.2f} / {t['p90_cm']:.2f} / {t['max_cm']:.2f} | "
              f"{o['median_cm']:.2f} / {o['p90_cm']:.2f} / {o['max_cm']:.2f} | {sim3} | "
              f"{r['scale_error_abs_median_percent']:.2f} / {r['scale_error_abs_max_percent']:.2f} | "
              f"{100 * r['tracked_fraction_min']:.1f} % | {r['runs_with_several_maps']} | {init} | {r['worst_run']} |")
    if paired:
        print()
        print("Paired, B / A per run (below 1: B better):")
        print()
        print("| preset | mode | pairs | refined: geomean, best, worst (run) | worse / better by >10 % |"
              " live: geomean, best, worst (run) | worse / better by >10 % |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for r in paired:
            cells = []
            for name in ("trajectory", "trajectory_online"):
                p = r[name]
                cells.append(f"{p['geomean']:.3f}, {p['best']:.2f}, {p['worst']:.2f} ({p['worst_run']})")
                cells.append(f"{p['worse_by_10_percent']} / {p['better_by_10_percent']}")
            print(f"| {r['preset']} | {r['mode']} | {r['pairs']} | " + " | ".join(cells) + " |")


def print_worst_runs(args, sweep, records):
    """The error over time of the worst runs (refined trajectory), drawn and summed up."""
    plots = sweep.out / "plots"
    plots.mkdir(exist_ok=True)
    draw = REPO / "tools" / "error_over_time.py"
    print()
    print(f"The {args.plots} worst runs per variant, preset and mode (refined trajectory; pictures in {plots}):")
    print()
    groups = {}
    for r in records:
        if not r.get("failed") and "trajectory" in r:
            groups.setdefault((r["variant"], r["preset"], r["mode"]), []).append(r)
    for (variant, preset, mode), runs in sorted(groups.items()):
        runs.sort(key=lambda r: -r["trajectory"]["ate_se3_m"])
        for r in runs[:args.plots]:
            name = f"{preset}-seed{r['seed']}-{r['agent']}-{mode}"
            build, _ = sweep.variants[variant]
            estimate = sweep.out / variant / name / "agent" / "trajectory.txt"
            groundtruth = sweep.mission_dir(preset, r["seed"]) / r["agent"]
            svg = plots / f"{variant}-{name}.svg"
            result = subprocess.run([sys.executable, str(draw), "--eval", str(build / "bin" / "cvislam_eval"),
                                     "--estimate", str(estimate), "--groundtruth", str(groundtruth), "--out", str(svg),
                                     "--title", f"{variant}: {preset} seed {r['seed']} {r['agent']} {mode}, SIMULATED"],
                                    capture_output=True, text=True)
            said = result.stdout.strip() if result.returncode == 0 else f"not drawn: {result.stderr.strip()}"
            print(f"- {variant} {preset} seed {r['seed']} {r['agent']} {mode} (maps {r.get('maps', 1)}, IMU "
                  f"initialised at {r.get('imu_init_s', -1):.2f} s): {said}")


def roudi_running():
    return subprocess.call(["pgrep", "-x", "iox-roudi"], stdout=subprocess.DEVNULL) == 0


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", default=str(REPO / "build" / "default"), help="A's build folder")
    parser.add_argument("--presets", default="loop,aggressive,euroc-mh",
                        help="cvislam_sim presets, comma-separated [loop,aggressive,euroc-mh]")
    parser.add_argument("--seeds", default="100-119", help="seeds and ranges, e.g. 100-119,130 [100-119]")
    parser.add_argument("--modes", default="mono,stereo", help="mono, stereo or both [mono,stereo]")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds per agent [60]")
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="runs at once, one per core [cores]")
    parser.add_argument("--config", help="cvislam_agent --config for A (and B unless --b-config)")
    parser.add_argument("--b-build", help="B's build folder (a paired comparison)")
    parser.add_argument("--b-config", help="B's --config (a paired comparison)")
    parser.add_argument("--out", help="results folder [$CVISLAM_SIM_CACHE/seeds/runs]")
    parser.add_argument("--plots", type=int, default=0,
                        help="draw the error over time of this many worst runs per variant, preset and mode into "
                             "OUT/plots/ (tools/error_over_time.py) and say what each shows [0]")
    args = parser.parse_args()
    args.presets = [p for p in args.presets.split(",") if p]
    args.modes = [m for m in args.modes.split(",") if m]
    args.seeds = parse_seeds(args.seeds)
    for m in args.modes:
        if m not in ("mono", "stereo"):
            sys.exit(f"agent_accuracy_seeds: --modes: {m!r} is neither mono nor stereo")
    if args.jobs < 1:
        sys.exit("agent_accuracy_seeds: --jobs must be at least 1")
    if args.plots < 0:
        sys.exit("agent_accuracy_seeds: --plots must be 0 or more")
    for build in {args.build, args.b_build or args.build}:
        for tool in ("cvislam_sim", "cvislam_agent", "cvislam_eval"):
            if not os.access(Path(build) / "bin" / tool, os.X_OK):
                sys.exit(f"agent_accuracy_seeds: {build}/bin/{tool} is missing: build it first (cmake --build {build})")
    for config in (args.config, args.b_config):
        if config and not Path(config).is_file():
            sys.exit(f"agent_accuracy_seeds: the config {config} does not exist")
    if shutil.which("iox-roudi") is None:
        sys.exit("agent_accuracy_seeds: iox-roudi is missing: run deploy/install_deps.sh")
    if roudi_running():
        sys.exit("agent_accuracy_seeds: an iox-roudi is running already; iceoryx allows one per machine and this "
                 "sweep starts its own: stop it first")

    sweep = Sweep(args)
    sweep.out.mkdir(parents=True, exist_ok=True)
    roudi_log = open(sweep.out / "roudi.log", "w")
    roudi = subprocess.Popen(["iox-roudi", "-m", "off", "-c", str(REPO / "deploy" / "roudi_config.toml")],
                             stdout=roudi_log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 10
        while "RouDi is ready" not in (sweep.out / "roudi.log").read_text():
            if roudi.poll() is not None or time.monotonic() > deadline:
                sys.exit(f"agent_accuracy_seeds: iox-roudi did not start: see {sweep.out / 'roudi.log'}")
            time.sleep(0.1)
        records = sweep.sweep()
    finally:
        roudi.terminate()
        roudi.wait()
    distribution = [row for v in sweep.variants for row in distribution_rows(records, v)]
    paired = paired_rows(records)
    (sweep.out / "report.json").write_text(
        json.dumps({"distribution": distribution, "paired": paired, "runs": records}, indent=1))
    print_report(args, sweep, distribution, paired)
    if args.plots:
        print_worst_runs(args, sweep, records)


if __name__ == "__main__":
    main()
