"""The refinement's energy and its gradient, compiled (numba): the terms of
:mod:`humotion.capture.refine` (its module docstring defines them), for one person over T frames.

Why by hand: the energy is some 150 small tensor operations (rotation vectors to matrices, the
skeleton level by level, keypoints, projection, the terms), and torch's autograd about doubles
them; each costs 5-30 us whatever its size, so an evaluation took about 5 ms at 90 frames, most
of it fixed, and L-BFGS makes some 300 of them per person. Here compiled loops compute the
energy (the skeleton's world rotations and positions by the body model's compiled
forward_kinematics, humotion.body.cpu_kernels) and, by reverse-mode differentiation written out
for the skeleton (from the leaves to the root), its gradient, in float64. tests/test_capture_refine.py holds the energy to the autograd
formulation of the module docstring and the gradient to finite differences.

Rotations: a joint's local rotation is R(v) = exp([v]x) of its rotation vector v (Rodrigues:
R = (1 - c a^2) I + s [v]x + c v v^T, a = |v|, s = sin a / a, c = (1 - cos a) / a^2), and
R(v + dv) = exp([J(v) dv]x) R(v) to first order, with J the left Jacobian of SO(3),
J(v) = s I + c [v]x + d v v^T, d = (a - sin a) / a^3. So a gradient G = dE/dR (3, 3) gives
dE/dv = J(v)^T tau, where tau is the axial vector of the skew part of G R^T.
"""

from __future__ import annotations

import math

import numpy as np

from humotion.body.cpu_kernels import forward_kinematics
from humotion.kernels import compiled, rodrigues

KEY, INIT, PRIOR, TEMPORAL, FLOOR, SKATE, SUPPORT, ROBUST = range(8)
"""Positions of the terms' weights (and E_key's robust scale) in the weights array."""


@compiled
def _coefficients(v0, v1, v2):
    """(s, c, d) of the module docstring for the rotation vector (v0, v1, v2), by series near 0."""
    a2 = v0 * v0 + v1 * v1 + v2 * v2
    if a2 < 1e-6:
        return 1.0 - a2 / 6.0, 0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0
    a = math.sqrt(a2)
    sin_a = math.sin(a)
    return sin_a / a, (1.0 - math.cos(a)) / a2, (a - sin_a) / (a2 * a)


@compiled
def _rotation_vector_gradient(v, s, c, d, gradient, rotation, out):
    """out (3,) += dE/dv for gradient (3, 3) = dE/dR at rotation (3, 3) = R(v), given v's
    coefficients s, c and d (module docstring)."""
    def skew_part(i, k):            # (G R^T)[i, k] - (G R^T)[k, i]
        return (gradient[i, 0] * rotation[k, 0] + gradient[i, 1] * rotation[k, 1] + gradient[i, 2] * rotation[k, 2]
                - gradient[k, 0] * rotation[i, 0] - gradient[k, 1] * rotation[i, 1] - gradient[k, 2] * rotation[i, 2])

    t0, t1, t2 = skew_part(2, 1), skew_part(0, 2), skew_part(1, 0)
    dot = v[0] * t0 + v[1] * t1 + v[2] * t2
    out[0] += s * t0 - c * (v[1] * t2 - v[2] * t1) + d * v[0] * dot
    out[1] += s * t1 - c * (v[2] * t0 - v[0] * t2) + d * v[1] * dot
    out[2] += s * t2 - c * (v[0] * t1 - v[1] * t0) + d * v[2] * dot


@compiled
def refinement_energy(theta, root, parents, rest, anchor_joints, anchor_offsets, camera, pixels, confidence, size,
                      network, prior_mean, prior_precision, weights, up, height, feet, soles, planted, held,
                      support_tolerance, theta_gradient, root_gradient):
    """The energy E (float) of humotion.capture.refine, and its gradient written into
    theta_gradient (T, J, 3) and root_gradient (T, 3). Arrays float64 unless said.

    theta (T, J, 3) local rotation vectors (joint 0: global, camera frame); root (T, 3) metres;
    parents (J,) int64, each before its children, -1 for joint 0; rest (1, J, 3) metres: the
    joints at rest, joint 0 at the origin;
    anchor_joints (K,) int64 and anchor_offsets (K, 3) metres: the keypoints' joints and offsets
    in their frames; camera (4,) fx, fy, cx, cy pixels; pixels (T, K, 2); confidence (T, K) in
    [0, 1]; size (T,) the person's 2D size, pixels; network (T, J, 3) metres, pelvis-relative;
    prior_mean (D,) and prior_precision (D, D) symmetric, over theta[:, 1:] flattened;
    weights (8,): KEY ... ROBUST; up (3,) unit and height metres: the floor, used when feet;
    soles (S,) int64 keypoint indices; planted (T, S) 0/1; held (T - 1, S) 0/1 (skating);
    support_tolerance metres."""
    frames, joint_count = theta.shape[0], theta.shape[1]
    keypoint_count = anchor_joints.shape[0]
    local = np.empty((frames, joint_count, 3, 3))
    coefficients = np.empty((frames, joint_count, 3))
    for t in range(frames):                                     # local rotations
        for j in range(joint_count):
            v = theta[t, j]
            coefficients[t, j] = _coefficients(v[0], v[1], v[2])
            rodrigues(v, coefficients[t, j, 0], coefficients[t, j, 1], local[t, j])
    world = np.empty((frames, joint_count, 3, 3))
    joints = np.empty((frames, joint_count, 3))
    forward_kinematics(local, rest, np.zeros((frames, 3)), parents, world, np.empty((frames, joint_count, 3)), joints)
    points = np.empty((frames, keypoint_count, 3))
    for t in range(frames):                                     # keypoints
        for k in range(keypoint_count):
            a = anchor_joints[k]
            for i in range(3):
                points[t, k, i] = (joints[t, a, i] + root[t, i] + world[t, a, i, 0] * anchor_offsets[k, 0]
                                   + world[t, a, i, 1] * anchor_offsets[k, 1] + world[t, a, i, 2] * anchor_offsets[k, 2])

    energy = 0.0
    point_gradient = np.zeros((frames, keypoint_count, 3))
    dims = prior_mean.shape[0]
    deviation = np.empty(dims)                                  # one frame's pose from the prior's mean
    joint_gradient = np.zeros((frames, joint_count, 3))
    theta_gradient[:] = 0.0
    root_gradient[:] = 0.0
    fx, fy, cx, cy = camera[0], camera[1], camera[2], camera[3]
    robust = weights[ROBUST]
    for t in range(frames):
        if weights[KEY] != 0.0:                                 # reprojection
            for k in range(keypoint_count):
                c = confidence[t, k]
                if c == 0.0:
                    continue
                x, y, z_true = points[t, k, 0], points[t, k, 1], points[t, k, 2]
                z = max(z_true, 1e-6)
                du = (fx * x / z + cx - pixels[t, k, 0]) / size[t]
                dv = (fy * y / z + cy - pixels[t, k, 1]) / size[t]
                squared = du * du + dv * dv
                slope = 1.0
                if robust != 0.0:
                    root_term = math.sqrt(1.0 + squared / (robust * robust))
                    squared = 2.0 * robust * robust * (root_term - 1.0)
                    slope = 1.0 / root_term
                energy += weights[KEY] * c * squared
                scale = weights[KEY] * c * slope * 2.0 / size[t]
                gu, gv = scale * du, scale * dv
                point_gradient[t, k, 0] += gu * fx / z
                point_gradient[t, k, 1] += gv * fy / z
                if z_true > 1e-6:
                    point_gradient[t, k, 2] -= (gu * fx * x + gv * fy * y) / (z * z)
        if weights[INIT] != 0.0:                                # closeness to the network
            for j in range(joint_count):
                for i in range(3):
                    d = joints[t, j, i] - network[t, j, i]
                    energy += weights[INIT] * d * d
                    joint_gradient[t, j, i] += 2.0 * weights[INIT] * d
        if weights[PRIOR] != 0.0:                               # the pose prior
            for n in range(dims):
                deviation[n] = theta[t, 1 + n // 3, n % 3] - prior_mean[n]
            for n in range(dims):
                row = 0.0
                for m in range(dims):
                    row += prior_precision[n, m] * deviation[m]
                energy += weights[PRIOR] * 0.5 * deviation[n] * row
                theta_gradient[t, 1 + n // 3, n % 3] += weights[PRIOR] * row
        if weights[TEMPORAL] != 0.0 and t > 0:                  # smooth joints in the camera frame
            for j in range(joint_count):
                for i in range(3):
                    d = joints[t, j, i] + root[t, i] - joints[t - 1, j, i] - root[t - 1, i]
                    energy += weights[TEMPORAL] * d * d
                    g = 2.0 * weights[TEMPORAL] * d
                    joint_gradient[t, j, i] += g
                    joint_gradient[t - 1, j, i] -= g
                    root_gradient[t, i] += g
                    root_gradient[t - 1, i] -= g
        if feet:
            lowest, lowest_sole = 1e300, 0
            for n in range(soles.shape[0]):
                k = soles[n]
                above = points[t, k, 0] * up[0] + points[t, k, 1] * up[1] + points[t, k, 2] * up[2] + height
                g = 0.0
                if weights[FLOOR] != 0.0:                       # planted soles on the floor, none under it
                    under = min(above, 0.0)
                    energy += weights[FLOOR] * (planted[t, n] * above * above + under * under)
                    g += 2.0 * weights[FLOOR] * (planted[t, n] * above + under)
                for i in range(3):
                    point_gradient[t, k, i] += g * up[i]
                if above < lowest:
                    lowest, lowest_sole = above, k
                if weights[SKATE] != 0.0 and t > 0 and held[t - 1, n] != 0.0:    # held soles do not slide
                    for i in range(3):
                        d = points[t, k, i] - points[t - 1, k, i]
                        energy += weights[SKATE] * held[t - 1, n] * d * d
                        g_slide = 2.0 * weights[SKATE] * held[t - 1, n] * d
                        point_gradient[t, k, i] += g_slide
                        point_gradient[t - 1, k, i] -= g_slide
            excess = lowest - support_tolerance
            if weights[SUPPORT] != 0.0 and excess > 0.0:        # some sole on the floor
                energy += weights[SUPPORT] * excess * excess
                for i in range(3):
                    point_gradient[t, lowest_sole, i] += 2.0 * weights[SUPPORT] * excess * up[i]

    world_gradient = np.zeros((joint_count, 3, 3))
    position_gradient = np.zeros((joint_count, 3))
    local_gradient = np.zeros((3, 3))
    for t in range(frames):                                     # reverse mode, leaves to root
        world_gradient[:] = 0.0
        position_gradient[:] = joint_gradient[t]
        for k in range(keypoint_count):
            a = anchor_joints[k]
            for i in range(3):
                g = point_gradient[t, k, i]
                root_gradient[t, i] += g
                position_gradient[a, i] += g
                for m in range(3):
                    world_gradient[a, i, m] += g * anchor_offsets[k, m]
        for j in range(joint_count - 1, -1, -1):
            p = parents[j]
            s, c, d = coefficients[t, j]
            if p < 0:
                _rotation_vector_gradient(theta[t, j], s, c, d, world_gradient[j], local[t, j], theta_gradient[t, j])
                continue
            for i in range(3):
                position_gradient[p, i] += position_gradient[j, i]
                for m in range(3):
                    world_gradient[p, i, m] += (position_gradient[j, i] * (rest[0, j, m] - rest[0, p, m])
                                                + world_gradient[j, i, 0] * local[t, j, m, 0]
                                                + world_gradient[j, i, 1] * local[t, j, m, 1]
                                                + world_gradient[j, i, 2] * local[t, j, m, 2])
            for i in range(3):                                  # dE/d(local) = world_parent^T dE/d(world)
                for m in range(3):
                    local_gradient[i, m] = (world[t, p, 0, i] * world_gradient[j, 0, m] + world[t, p, 1, i] * world_gradient[j, 1, m]
                                            + world[t, p, 2, i] * world_gradient[j, 2, m])
            _rotation_vector_gradient(theta[t, j], s, c, d, local_gradient, local[t, j], theta_gradient[t, j])
    return energy
