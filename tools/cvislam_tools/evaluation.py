"""cvislam_eval as a subprocess: its JSON for (estimate, ground truth) pairs, and the ATE from it."""

import json
import subprocess


def run_eval(eval_bin, pairs, json_path, align=None, per_pose=False):
    """cvislam_eval over (estimate, ground truth) pairs, its JSON written to json_path: (the JSON, None), or
    (None, why not) when it failed."""
    cmd = [eval_bin, "--quiet", "--json", json_path]
    for estimate, groundtruth in pairs:
        cmd += ["--estimate", estimate, "--groundtruth", groundtruth]
    if align:
        cmd += ["--align", align]
    if per_pose:
        cmd.append("--per-pose")
    result = subprocess.run(cmd, capture_output=True, text=True)  # a missing cvislam_eval raises: a setup error
    if result.returncode != 0:
        reason = (result.stderr or result.stdout).strip().splitlines()
        return None, reason[-1] if reason else "cvislam_eval failed"
    try:
        with open(json_path) as f:
            return json.load(f), None
    except (OSError, ValueError) as e:
        return None, f"its JSON is unreadable: {e}"


def ate(evaluation, alignment="se3"):
    """The ATE RMSE [m] after `alignment` (se3, sim3, posyaw) of a cvislam_eval JSON; NaN without one."""
    return evaluation[alignment]["rmse"] if evaluation and alignment in evaluation else float("nan")
