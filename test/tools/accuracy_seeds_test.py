#!/usr/bin/python3
"""test/bench/agent_accuracy_seeds.py: the first motion is found in a recording's ground truth, and the IMU
initialisation is reported from the first image and from the first motion (standard library only)."""

import importlib.util
import os
import tempfile
import unittest
from pathlib import Path

_SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "agent_accuracy_seeds.py"
_SPEC = importlib.util.spec_from_file_location("agent_accuracy_seeds", _SCRIPT)
seeds = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(seeds)

T0_NS = 1_600_000_000_000_000_000


def write_recording(folder, first_image_s, still_until_s, speed_m_s=0.3):
    """An EuRoC-style agent folder: images at 20 Hz from first_image_s, and ground truth at 200 Hz from 0 s that
    stands still (a jitter of 5 mm/s, as EuRoC's on the floor) until still_until_s and then moves at speed_m_s."""
    cam = Path(folder) / "mav0" / "cam0"
    gt = Path(folder) / "mav0" / "state_groundtruth_estimate0"
    cam.mkdir(parents=True)
    gt.mkdir(parents=True)
    with open(cam / "data.csv", "w") as f:
        f.write("#timestamp [ns],filename\n")
        for i in range(100):
            t_ns = T0_NS + int((first_image_s + 0.05 * i) * 1e9)
            f.write(f"{t_ns},{t_ns}.png\n")
    with open(gt / "data.csv", "w") as f:
        f.write("#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z\n")
        for i in range(1200):
            t = 0.005 * i
            v = speed_m_s if t >= still_until_s else 0.005 * (-1) ** i
            f.write(f"{T0_NS + int(t * 1e9)},0,0,0,1,0,0,0,{v},0,0,0,0,0,0,0,0\n")


def record(seed, imu_init_s, first_motion_s):
    run = {"ate_se3_m": 0.01, "scale_error_percent": 0.1}
    return {"variant": "A", "preset": "euroc-mh", "mode": "mono", "seed": seed, "agent": "agent4", "failed": False,
            "frames": 100, "tracked": 100, "maps": 1, "imu_init_s": imu_init_s, "first_motion_s": first_motion_s,
            "trajectory": run, "trajectory_online": run}


class FirstMotionTest(unittest.TestCase):
    def test_a_recording_that_stands_still_first_moves_when_its_speed_reaches_the_threshold(self):
        with tempfile.TemporaryDirectory() as folder:
            write_recording(folder, first_image_s=0.2, still_until_s=2.5)
            self.assertAlmostEqual(seeds.first_motion_s(folder), 2.3, delta=0.006)

    def test_a_recording_that_moves_from_its_first_image_has_its_first_motion_there(self):
        with tempfile.TemporaryDirectory() as folder:
            write_recording(folder, first_image_s=0.5, still_until_s=0.0)
            self.assertEqual(seeds.first_motion_s(folder), 0.0)

    def test_the_report_gives_the_initialisation_from_the_first_image_and_from_the_first_motion(self):
        rows = seeds.distribution_rows([record(100, 4.8, 2.7), record(101, 2.2, 0.0), record(102, 2.4, 0.0)], "A")
        self.assertEqual(len(rows), 1)
        self.assertAlmostEqual(rows[0]["imu_init_median_s"], 2.4)
        self.assertAlmostEqual(rows[0]["imu_init_max_s"], 4.8)
        self.assertAlmostEqual(rows[0]["imu_init_after_motion_median_s"], 2.2)
        self.assertAlmostEqual(rows[0]["imu_init_after_motion_max_s"], 2.4)


if __name__ == "__main__":
    unittest.main()
