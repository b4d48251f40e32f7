"""The run outputs' file formats: JSON, numeric tables (TUM trajectories, CSV), TUM rows as written, and EuRoC
ground truth. Readers return None (or skip the row) where a file or row is missing or malformed, so that a failed
agent or a server that wrote nothing costs a line of the report, not the report."""

import json
import os

# Where a EuRoC/ASL sequence keeps its ground truth: the simulator's missions and the excerpt have mav0/, a bare
# sequence folder may not.
GROUNDTRUTH_FILES = ("mav0/state_groundtruth_estimate0/data.csv", "state_groundtruth_estimate0/data.csv")


def load_json(path):
    """The JSON in path, or None when it is missing or unreadable."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def read_rows(path, sep=None, columns=4):
    """Numeric rows (their first `columns` values) of a text table; comments, headers and bad rows are skipped.
    Returns None when the file cannot be read."""
    rows = []
    try:
        with open(path) as f:
            for line in f:
                if line.startswith("#"):
                    continue
                values = line.strip().split(sep)
                try:
                    rows.append([float(v) for v in values[:columns]])
                except ValueError:
                    continue
    except OSError:
        return None
    return [r for r in rows if len(r) == columns]


def read_csv(path):
    """A CSV with a header as a list of dicts, or None when it cannot be read."""
    try:
        with open(path) as f:
            header = f.readline().strip().split(",")
            return [dict(zip(header, line.strip().split(","))) for line in f
                    if len(line.strip().split(",")) == len(header)]
    except OSError:
        return None


def read_tum_fields(path):
    """The rows of a TUM file ("t[s] x y z qx qy qz qw") as the strings written, so that the times of two files
    compare exactly, with repeats kept; None when the file cannot be read."""
    try:
        with open(path) as f:
            return [line.split() for line in f if line.strip() and not line.strip().startswith("#")]
    except OSError:
        return None


def groundtruth_path(sequence):
    """The ground-truth CSV of a EuRoC/ASL sequence folder, or None when it has none."""
    for sub in GROUNDTRUTH_FILES:
        path = os.path.join(sequence, sub)
        if os.path.exists(path):
            return path
    return None


def read_groundtruth(sequence):
    """A sequence's ground truth as (t_ns, (x, y, z), (qw, qx, qy, qz)) rows, times exact as integers; None when
    there is none. Rows that are not eight numbers at least are skipped."""
    path = groundtruth_path(sequence)
    if path is None:
        return None
    rows = []
    try:
        with open(path) as f:
            for line in f:
                if not line.strip() or line.startswith("#"):
                    continue
                v = line.strip().split(",")
                try:
                    rows.append((int(v[0]), (float(v[1]), float(v[2]), float(v[3])),
                                 (float(v[4]), float(v[5]), float(v[6]), float(v[7]))))  # EuRoC order: w, x, y, z
                except (ValueError, IndexError):
                    continue
    except OSError:
        return None
    return rows
