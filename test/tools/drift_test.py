#!/usr/bin/python3
"""tools/cvislam_tools/drift.py: on trajectories with a known heading drift and a known scale error, the windows'
yaw and scale come out as made; windows where the sensor stands still are left out."""

import math
import os
import sys
import unittest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "tools"))
from cvislam_tools import drift  # noqa: E402


def circle(t):
    """A 2 m circle in 20 s, with a slow climb."""
    a = 2 * math.pi * t / 20.0
    return [2.0 * math.cos(a), 2.0 * math.sin(a), 1.0 + 0.01 * t]


def rotate_z(p, deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]]


class DriftTest(unittest.TestCase):
    def test_a_heading_that_turns_steadily_shows_as_a_growing_yaw(self):
        times = [0.05 * i for i in range(1200)]  # 60 s at 20 Hz
        gt = [circle(t) for t in times]
        # Dead reckoning whose heading turns by -3 deg per minute against the truth: each step is the true one,
        # turned by the heading error at its time.
        est = [list(gt[0])]
        for i in range(1, len(times)):
            step = [g - h for g, h in zip(gt[i], gt[i - 1])]
            turned = rotate_z(step, -3.0 * times[i] / 60.0)
            est.append([e + d for e, d in zip(est[-1], turned)])
        fits = drift.window_fits(times, est, gt, window_s=5.0, step_s=5.0)
        self.assertEqual(len(fits), 11)  # the last window would end after the last pose
        for centre, yaw_deg, scale_percent in fits:
            # Mapping the estimate back onto the truth turns it by +3 deg per minute, by the window's centre.
            self.assertAlmostEqual(yaw_deg, 3.0 * centre / 60.0, delta=0.05)
            self.assertAlmostEqual(scale_percent, 0.0, delta=0.05)

    def test_an_estimate_too_large_by_two_percent_shows_a_scale_error_of_two_percent(self):
        times = [0.05 * i for i in range(600)]
        gt = [circle(t) for t in times]
        est = [[1.02 * c for c in p] for p in gt]
        fits = drift.window_fits(times, est, gt, window_s=5.0, step_s=1.0)
        self.assertGreater(len(fits), 20)
        for _, yaw_deg, scale_percent in fits:
            self.assertAlmostEqual(scale_percent, 2.0, delta=0.01)
            self.assertAlmostEqual(yaw_deg, 0.0, delta=1e-6)
        d = drift.diagnose(times, est, gt)
        self.assertAlmostEqual(d["scale_error_range_percent"][0], 2.0, delta=0.01)
        self.assertAlmostEqual(d["scale_error_range_percent"][1], 2.0, delta=0.01)

    def test_windows_where_the_sensor_stands_still_are_left_out(self):
        times = [0.05 * i for i in range(600)]  # 20 s moving, then 10 s still
        gt = [circle(min(t, 20.0)) for t in times]
        est = [list(p) for p in gt]
        fits = drift.window_fits(times, est, gt, window_s=5.0, step_s=1.0)
        self.assertTrue(fits)
        self.assertTrue(all(centre < 22.5 for centre, _, _ in fits), fits[-1])

    def test_position_errors_split_into_horizontal_and_vertical(self):
        errors = drift.position_errors([[0.03, 0.04, 1.0]], [[0.0, 0.0, 0.98]])
        self.assertAlmostEqual(errors[0][0], 0.05)
        self.assertAlmostEqual(errors[0][1], 0.02)


if __name__ == "__main__":
    unittest.main()
