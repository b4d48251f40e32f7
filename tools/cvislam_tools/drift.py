"""Where a trajectory's error comes from, over time.

A whole-run SE3 alignment gives one ATE figure. To see what made it, the error is split up over time:
  - the position error of every pose after that alignment, horizontal and vertical;
  - in windows of a few seconds, the estimate's best fit onto the ground truth by a yaw rotation about gravity and
    a scale (positions centred in the window): the yaw says how far the heading has turned from the whole run's
    alignment by then, the scale how far the local scale is off. A constant scale error with a yaw that stays put
    is a scale problem (mono initialisation); a yaw that keeps turning is heading drift; an error that is there
    from the first metric pose and does not grow comes from the initialisation.

Pure Python on the per-pose output of cvislam_eval (--per-pose): estimate positions after the SE3 alignment and the
ground truth's, with their timestamps.
"""

import math


def load_per_pose(evaluation):
    """(times [s] from the first pose, aligned estimate xyz, ground truth xyz) of a cvislam_eval --per-pose JSON."""
    stamps = [float(t) for t in evaluation["timestamps_s"]]
    t0 = stamps[0] if stamps else 0.0
    return ([t - t0 for t in stamps], evaluation["estimate_se3_aligned_xyz_m"], evaluation["groundtruth_xyz_m"])


def position_errors(est, gt):
    """Per pose: (horizontal, vertical) error [m]."""
    out = []
    for e, g in zip(est, gt):
        out.append((math.hypot(e[0] - g[0], e[1] - g[1]), abs(e[2] - g[2])))
    return out


def yaw_scale_fit(est, gt):
    """The yaw [rad] and scale that best map the centred estimate positions onto the centred ground truth
    (least squares, yaw about z only), and the ground truth's spread [m] (the RMS distance from its centre): the
    fit says little when that spread is small. None for fewer than 3 poses."""
    n = len(est)
    if n < 3:
        return None
    ce = [sum(p[i] for p in est) / n for i in range(3)]
    cg = [sum(p[i] for p in gt) / n for i in range(3)]
    a = [[p[i] - ce[i] for i in range(3)] for p in est]
    b = [[p[i] - cg[i] for i in range(3)] for p in gt]
    cos_sum = sum(x[0] * y[0] + x[1] * y[1] for x, y in zip(a, b))
    sin_sum = sum(x[0] * y[1] - x[1] * y[0] for x, y in zip(a, b))
    yaw = math.atan2(sin_sum, cos_sum)
    c, s = math.cos(yaw), math.sin(yaw)
    rotated = [(c * x[0] - s * x[1], s * x[0] + c * x[1], x[2]) for x in a]
    norm = sum(x[0] ** 2 + x[1] ** 2 + x[2] ** 2 for x in rotated)
    if norm <= 0.0:
        return None
    scale = sum(r[0] * y[0] + r[1] * y[1] + r[2] * y[2] for r, y in zip(rotated, b)) / norm
    spread = math.sqrt(sum(y[0] ** 2 + y[1] ** 2 + y[2] ** 2 for y in b) / n)
    return yaw, scale, spread


def window_fits(times, est, gt, window_s=5.0, step_s=1.0, min_spread_m=0.2):
    """Per window of `window_s` seconds, every `step_s`: (centre time [s], yaw [deg], scale error [%]). Windows
    whose ground truth spreads less than `min_spread_m` (the sensor nearly still) are left out."""
    out = []
    if not times:
        return out
    start, end = times[0], times[-1]
    lo = 0
    t = start
    while t + window_s <= end + 1e-9:
        while lo < len(times) and times[lo] < t:
            lo += 1
        hi = lo
        while hi < len(times) and times[hi] <= t + window_s:
            hi += 1
        fit = yaw_scale_fit(est[lo:hi], gt[lo:hi])
        if fit is not None and fit[2] >= min_spread_m:
            yaw, scale, _ = fit
            out.append((t + window_s / 2, math.degrees(yaw), 100.0 * (1.0 / scale - 1.0)))
        t += step_s
    return out


def diagnose(times, est, gt, window_s=5.0):
    """What the error over time says, as numbers: the error at the first pose and its largest value [m], when that
    was [s], and the range of the windows' yaw [deg] and scale error [%] (None without a window)."""
    errors = [math.hypot(h, v) for h, v in position_errors(est, gt)]
    if not errors:
        return None
    worst = max(range(len(errors)), key=lambda i: errors[i])
    fits = window_fits(times, est, gt, window_s)
    out = {"first_error_m": errors[0], "max_error_m": errors[worst], "max_error_at_s": times[worst],
           "windows": len(fits), "yaw_range_deg": None, "scale_error_range_percent": None}
    if fits:
        yaws = [f[1] for f in fits]
        scales = [f[2] for f in fits]
        out["yaw_range_deg"] = (min(yaws), max(yaws))
        out["scale_error_range_percent"] = (min(scales), max(scales))
    return out
