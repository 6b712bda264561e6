"""numba kernels of the arm's geometry (see `arm`): capsule distances and link speeds.

Both run every control period of the bridge and of the batch cell, so they loop over scalars
and allocate nothing per pair.

`capsule_separation`: for each arm capsule i and body capsule j the closest points c1, c2 of
their axis segments (Ericson, Real-Time Collision Detection, 5.1.9: s, t minimising
|p0 + s d1 - q0 - t d2| over [0, 1]^2, clamped, degenerate segments included), the surface
distance |c2 - c1| - r_i - r_j, and the pair with the smallest.

`link_speed`: the fastest point of the arm's capsules, max over the capsules' ends e of
|sum_{j moves e} qd_j z_j x (e - o_j)| plus the capsule's spin |omega| r.
"""

from __future__ import annotations

import math

import numba
import numpy as np

EPS = 1e-12


@numba.njit(cache=True)
def _closest(p0, p1, q0, q1, out1, out2):
    d1x, d1y, d1z = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    d2x, d2y, d2z = q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2]
    rx, ry, rz = p0[0] - q0[0], p0[1] - q0[1], p0[2] - q0[2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    if a <= EPS and e <= EPS:
        s = 0.0
        t = 0.0
    elif a <= EPS:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= EPS:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            if denom > EPS * a * e:
                s = min(max((b * f - c * e) / denom, 0.0), 1.0)
            else:
                s = 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    out1[0] = p0[0] + d1x * s
    out1[1] = p0[1] + d1y * s
    out1[2] = p0[2] + d1z * s
    out2[0] = q0[0] + d2x * t
    out2[1] = q0[1] + d2y * t
    out2[2] = q0[2] + d2z * t


@numba.njit(cache=True)
def capsule_separation(arm_segments, arm_radii, body_segments, body_radii, points, surface):
    """(surface distance, i, j) of the closest arm/body capsule pair; with `surface`, `points`
    (2, 3) receives the closest points on the two capsules' surfaces (on the arm's, on the
    body's), moved from their axes by the radii along the line between them."""
    c1 = np.empty(3)
    c2 = np.empty(3)
    best = np.inf
    best_i = 0
    best_j = 0
    for i in range(arm_segments.shape[0]):
        for j in range(body_segments.shape[0]):
            _closest(arm_segments[i, 0], arm_segments[i, 1], body_segments[j, 0],
                     body_segments[j, 1], c1, c2)
            gx, gy, gz = c2[0] - c1[0], c2[1] - c1[1], c2[2] - c1[2]
            dist = math.sqrt(gx * gx + gy * gy + gz * gz) - arm_radii[i] - body_radii[j]
            if dist < best:
                best = dist
                best_i = i
                best_j = j
                points[0, :] = c1
                points[1, :] = c2
    if surface:
        gx = points[1, 0] - points[0, 0]
        gy = points[1, 1] - points[0, 1]
        gz = points[1, 2] - points[0, 2]
        length = math.sqrt(gx * gx + gy * gy + gz * gz)
        if length > EPS:
            gx, gy, gz = gx / length, gy / length, gz / length
        else:
            gx, gy, gz = 1.0, 0.0, 0.0
        ra = arm_radii[best_i]
        rb = body_radii[best_j]
        points[0, 0] += ra * gx
        points[0, 1] += ra * gy
        points[0, 2] += ra * gz
        points[1, 0] -= rb * gx
        points[1, 1] -= rb * gy
        points[1, 2] -= rb * gz
    return best, best_i, best_j


@numba.njit(cache=True)
def link_speed(segments, radii, last_joint, axes, anchors, qd):
    """The fastest point of the capsules (m/s): capsule c is moved by joints 0..last_joint[c]."""
    best = 0.0
    for c in range(segments.shape[0]):
        wx = 0.0
        wy = 0.0
        wz = 0.0
        for j in range(last_joint[c] + 1):
            wx += axes[j, 0] * qd[j]
            wy += axes[j, 1] * qd[j]
            wz += axes[j, 2] * qd[j]
        spin = math.sqrt(wx * wx + wy * wy + wz * wz) * radii[c]
        for end in range(2):
            vx = 0.0
            vy = 0.0
            vz = 0.0
            for j in range(last_joint[c] + 1):
                lx = segments[c, end, 0] - anchors[j, 0]
                ly = segments[c, end, 1] - anchors[j, 1]
                lz = segments[c, end, 2] - anchors[j, 2]
                vx += qd[j] * (axes[j, 1] * lz - axes[j, 2] * ly)
                vy += qd[j] * (axes[j, 2] * lx - axes[j, 0] * lz)
                vz += qd[j] * (axes[j, 0] * ly - axes[j, 1] * lx)
            speed = math.sqrt(vx * vx + vy * vy + vz * vz) + spin
            if speed > best:
                best = speed
    return best


@numba.njit(cache=True)
def capsule_ends(centres, xmats, half_lengths, out):
    """Axis ends (n, 2, 3) of capsules from MuJoCo's geom_xpos and geom_xmat rows."""
    for c in range(centres.shape[0]):
        for k in range(3):
            h = half_lengths[c] * xmats[c, 3 * k + 2]
            out[c, 0, k] = centres[c, k] - h
            out[c, 1, k] = centres[c, k] + h


@numba.njit(cache=True)
def path_offset(q, positions, direction):
    """(the largest joint's distance from `q` to the polyline through `positions` (n, 6), at
    the Euclidean projection on each segment, the smallest over the segments; the index of
    that segment, -1 for a path of one point) with the unit direction of that segment in
    `direction` (zeros for one point). `guard.nearest_on_path` in a loop of scalars."""
    n, m = positions.shape
    best = np.inf
    best_i = -1
    if n == 1:
        best = 0.0
        for k in range(m):
            d = abs(q[k] - positions[0, k])
            if d > best:
                best = d
            direction[k] = 0.0
        return best, -1
    for i in range(n - 1):
        length2 = 0.0
        dot = 0.0
        for k in range(m):
            step = positions[i + 1, k] - positions[i, k]
            length2 += step * step
            dot += (q[k] - positions[i, k]) * step
        u = 0.0
        if length2 > 0.0:
            u = min(max(dot / length2, 0.0), 1.0)
        off = 0.0
        for k in range(m):
            d = abs(q[k] - positions[i, k] - u * (positions[i + 1, k] - positions[i, k]))
            if d > off:
                off = d
        if off < best:
            best = off
            best_i = i
    length2 = 0.0
    for k in range(m):
        step = positions[best_i + 1, k] - positions[best_i, k]
        length2 += step * step
    norm = math.sqrt(length2)
    for k in range(m):
        direction[k] = 0.0 if norm == 0.0 else \
            (positions[best_i + 1, k] - positions[best_i, k]) / norm
    return best, best_i
