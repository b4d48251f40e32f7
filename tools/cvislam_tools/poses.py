"""Quaternions and rigid poses in plain tuples.

A quaternion is (w, x, y, z) unless a function says otherwise; a pose T is (quaternion, translation) and maps a
point p to R(q) p + t, as cvislam_eval's transforms do (common/eval/report.cpp)."""

import math


def quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def quat_inv(q):
    """The inverse of a unit quaternion (its conjugate)."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_rotate(q, v):
    w, x, y, z = quat_mul(quat_mul(q, (0.0, *v)), quat_inv(q))
    return (x, y, z)


def quat_to_matrix(w, x, y, z):
    """The rotation matrix (rows) of a quaternion, normalised first; ValueError for the zero quaternion."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0.0:
        raise ValueError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def angle_between_deg(a, b):
    """The angle of the rotation between two unit quaternions, in degrees. Both in the same component order (any:
    it is 2 acos |a . b|), so TUM's (x, y, z, w) rows compare as they are; q and -q are the same rotation."""
    return math.degrees(2.0 * math.acos(min(1.0, abs(sum(p * q for p, q in zip(a, b))))))


def pose_apply(T, p):
    r = quat_rotate(T[0], p)
    return tuple(r[i] + T[1][i] for i in range(3))


def pose_inv(T):
    qi = quat_inv(T[0])
    t = quat_rotate(qi, T[1])
    return (qi, tuple(-c for c in t))


def pose_mul(A, B):
    return (quat_mul(A[0], B[0]), pose_apply(A, B[1]))


def relative_translation(R_a, t_a, t_b):
    """(T_a^-1 T_b).translation = R_a^T (t_b - t_a), with R_a as rows (quat_to_matrix)."""
    d = [t_b[i] - t_a[i] for i in range(3)]
    return [sum(R_a[r][c] * d[r] for r in range(3)) for c in range(3)]


def eval_transform(transform):
    """cvislam_eval's transform JSON ({"quaternion_wxyz", "translation", "scale"}, S_gt_est of an alignment) as
    (quaternion, translation, scale); KeyError, TypeError or ValueError when it is not one."""
    q = tuple(float(v) for v in transform["quaternion_wxyz"])
    t = tuple(float(v) for v in transform["translation"])
    if len(q) != 4 or len(t) != 3:
        raise ValueError("a transform has 4 quaternion and 3 translation values")
    return q, t, float(transform.get("scale", 1.0))
