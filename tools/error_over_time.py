#!/usr/bin/python3
"""Draws where a trajectory's error comes from over time (cvislam_tools/drift.py): the position error after the
whole run's SE3 alignment, horizontal and vertical; and, in windows of a few seconds, the heading (yaw) the
estimate has turned by from that alignment and its scale error. Prints the same as numbers.

    error_over_time.py --eval BUILD/bin/cvislam_eval --estimate trajectory.txt --groundtruth GT --out error.svg
        [--title TEXT] [--window-s 5]

The estimate is scored as cvislam_eval scores it (frames marked as before the IMU initialisation left out)."""

import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from cvislam_tools import drift  # noqa: E402
from mission_pictures import Frame, esc, legend, nice_step, svg_document  # noqa: E402

WIDTH = 760
PANEL_H = 150
LEFT = 70


def panel(frame_top, times, series, ylabel, colours, labels, zero_line=False):
    """One plot of several series [(t, value)] over the run's time; returns (elements, its height)."""
    values = [v for s in series for _, v in s] or [0.0]
    lo, hi = min(values + [0.0]), max(values + [0.0])
    if hi - lo < 1e-9:
        hi = lo + 1.0
    pad = 0.05 * (hi - lo)
    xr = (0.0, max(times[-1] if times else 1.0, 1e-6))
    f = Frame(LEFT, frame_top, WIDTH - LEFT - 20, PANEL_H, xr, (lo - pad, hi + pad))
    out = f.axes(nice_step(xr[1] - xr[0]), nice_step(hi - lo + 2 * pad, 5), "", ylabel)
    if zero_line:
        out.append(f.polyline([(xr[0], 0.0), (xr[1], 0.0)], "#999", 1.0, "stroke-dasharray='4 3'"))
    for s, colour in zip(series, colours):
        if len(s) > 1:
            out.append(f.polyline(s, colour))
    items, _ = legend([(label, "line", colour) for label, colour in zip(labels, colours)], LEFT + 8,
                      frame_top + 16, WIDTH - LEFT - 40)
    return out + items, PANEL_H + 30


def draw(times, est, gt, title, window_s):
    errors = drift.position_errors(est, gt)
    fits = drift.window_fits(times, est, gt, window_s)
    body = [f"<text x='20' y='24' font-size='14' font-weight='bold'>{esc(title)}</text>"]
    top = 44
    elements, used = panel(top, times, [[(t, 100 * h) for t, (h, _) in zip(times, errors)],
                                        [(t, 100 * v) for t, (_, v) in zip(times, errors)]],
                           "error [cm]", ["#1f77b4", "#d62728"], ["horizontal", "vertical"])
    body += elements
    top += used
    elements, used = panel(top, times, [[(t, y) for t, y, _ in fits]], "yaw [deg]", ["#2ca02c"],
                           [f"heading turned, {window_s:g} s windows"], zero_line=True)
    body += elements
    top += used
    elements, used = panel(top, times, [[(t, s) for t, _, s in fits]], "scale error [%]", ["#ff7f0e"],
                           [f"scale error, {window_s:g} s windows"], zero_line=True)
    body += elements
    top += used
    body.append(f"<text x='{LEFT + (WIDTH - LEFT - 20) / 2:.0f}' y='{top - 8}' text-anchor='middle'>"
                "time from the first scored pose [s]</text>")
    return svg_document(WIDTH, top + 10, body, title)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--eval", required=True, help="the cvislam_eval executable")
    parser.add_argument("--estimate", required=True, help="the trajectory (TUM or EuRoC CSV)")
    parser.add_argument("--groundtruth", required=True, help="its ground truth (file or EuRoC/ASL folder)")
    parser.add_argument("--out", required=True, help="the SVG to write")
    parser.add_argument("--title", default="", help="the picture's title [the estimate's path]")
    parser.add_argument("--window-s", type=float, default=5.0, help="the yaw and scale windows [5 s]")
    args = parser.parse_args()
    if not args.window_s > 0:
        sys.exit("error_over_time: --window-s must be > 0")
    with tempfile.TemporaryDirectory() as tmp:
        scored = os.path.join(tmp, "eval.json")
        result = subprocess.run([args.eval, "--estimate", args.estimate, "--groundtruth", args.groundtruth,
                                 "--per-pose", "--json", scored, "--quiet"], capture_output=True, text=True)
        if result.returncode != 0:
            sys.exit(f"error_over_time: cvislam_eval failed on {args.estimate}: {result.stderr.strip()}")
        with open(scored) as f:
            evaluation = json.load(f)
    times, est, gt = drift.load_per_pose(evaluation)
    if len(times) < 3:
        sys.exit(f"error_over_time: {args.estimate}: fewer than 3 poses scored")
    with open(args.out, "w") as f:
        f.write(draw(times, est, gt, args.title or args.estimate, args.window_s))
    d = drift.diagnose(times, est, gt, args.window_s)
    line = (f"ATE {100 * evaluation['se3']['rmse']:.2f} cm; error at the first pose {100 * d['first_error_m']:.2f} cm, "
            f"largest {100 * d['max_error_m']:.2f} cm at {d['max_error_at_s']:.1f} s")
    if d["windows"]:
        line += (f"; over {d['windows']} windows of {args.window_s:g} s the heading turned "
                 f"{d['yaw_range_deg'][0]:+.2f} to {d['yaw_range_deg'][1]:+.2f} deg and the scale error was "
                 f"{d['scale_error_range_percent'][0]:+.2f} to {d['scale_error_range_percent'][1]:+.2f} %")
    print(line)


if __name__ == "__main__":
    main()
