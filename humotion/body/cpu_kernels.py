"""The compiled loops (numba) of the body model's CPU inference path: functions of numpy arrays,
each documenting its arrays, called by :mod:`humotion.body.cpu_posing` (which imports this module
on first use: importing it imports numba). Each loop compiles on its first call, or loads from
numba's disk cache.

Float16 weights: the body model's big matrices (the shape and expression decoders' output
layers, the pose correctives' regressor) hold float16 numbers exactly, since the shipped weights
are stored as float16 (:func:`humotion.model_files.save_model_file`), so products with float16
copies of them give the same sums from half the bytes. For a few bodies such a product only
streams its matrix from memory, so :func:`half_product` is faster than torch's float32 product
on one thread up to batch 4, and slower from batch 8 on (the body model card's Speed section;
`bench/body_products.py`).
"""

from __future__ import annotations

import platform

import numpy as np
from llvmlite import binding, ir
from numba import types
from numba.core import config
from numba.extending import intrinsic, overload

from humotion.kernels import compiled


def _converts_float16_in_hardware() -> bool:
    """Whether numba compiles for an x86-64 CPU with F16C, whose instructions convert float16 to
    float32 (numba's target: NUMBA_CPU_NAME / NUMBA_CPU_FEATURES, else this machine's CPU;
    NUMBA_CPU_NAME=generic, set for caches shared between machines, has no F16C)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    features = config.CPU_FEATURES if config.CPU_FEATURES is not None else binding.get_host_cpu_features().flatten()
    return "+f16c" in features.split(",")


FLOAT16_IN_HARDWARE = _converts_float16_in_hardware()
"""Whether the float16 loops may run here (:func:`half_to_float`); where not, the CPU path keeps
its products in float32 (:func:`humotion.body.cpu_posing.uses_float16`). Not tried on ARM, where
they are not used either."""


@intrinsic
def half_to_float(typing_context, bits):
    """float32 of the float16 whose bits (uint16) are given, in compiled code (numba has no
    float16 type; LLVM turns this into x86's F16C conversion, eight or sixteen at a time). Only
    where FLOAT16_IN_HARDWARE: without F16C, LLVM calls a runtime function that numba does not
    link, and the process crashes."""
    signature = types.float32(types.uint16)

    def codegen(context, builder, _signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return signature, codegen


def to_float32(value):
    """float32 of a float16's bits (uint16) or of a float32, in compiled code, where the overload
    below picks the conversion by type: a loop compiled for float32 arrays holds no float16
    conversion, and runs where FLOAT16_IN_HARDWARE does not hold. (Compiled code only.)"""
    raise NotImplementedError("to_float32 is implemented for numba-compiled loops only")


@overload(to_float32)
def _to_float32_compiled(value):
    if isinstance(value, types.Integer):
        return lambda value: half_to_float(value)
    return lambda value: value


@compiled
def half_product(weight, factors, offset, out):
    """weight (R, K) uint16, float16 bits; factors (B, K) f32; offset (R, 1 or B) f32, or (0, 1)
    for none -> out (R, B) f32 offset + weight @ factors.T (sums in float32)."""
    has_offset, shared_offset = offset.shape[0] > 0, offset.shape[1] == 1
    for r in range(weight.shape[0]):
        for b in range(factors.shape[0]):
            total = np.float32(0.0)
            for k in range(weight.shape[1]):
                total += half_to_float(weight[r, k]) * factors[b, k]
            if has_offset:
                total += offset[r, 0 if shared_offset else b]
            out[r, b] = total


@compiled
def pose_block(surface, moves, move_rows, transforms, bones, weights, out):
    """surface (n, 3, B) f32 rest + correctives (m); moves (E, 3, B) f32 expression offsets (m)
    and move_rows (n,) i32, each vertex's row in moves or -1; transforms (J, 12 B) f32, per
    bone its A (3 x 3, row-major) then t, each of the 12 numbers for the B bodies in a row;
    bones (n, S) i32 and weights (n, S) f32 each vertex's skinning; out (n, 3, B) f32."""
    n, _, batch = surface.shape
    entries, support = transforms.shape[1], bones.shape[1]
    blended = np.empty(entries, np.float32)
    for v in range(n):
        blended[:] = 0.0
        for s in range(support):
            weight = weights[v, s]
            if weight == 0.0:   # (an early continue: an if-block around the loop ran 2.4x slower)
                continue
            bone = transforms[bones[v, s]]
            for i in range(entries):
                blended[i] += weight * bone[i]
        for c in range(3):
            rotation, translation = 3 * c * batch, (9 + c) * batch
            for b in range(batch):
                out[v, c, b] = (blended[rotation + b] * surface[v, 0, b]
                                + blended[rotation + batch + b] * surface[v, 1, b]
                                + blended[rotation + 2 * batch + b] * surface[v, 2, b] + blended[translation + b])
        row = move_rows[v]
        if row >= 0:   # the expression's offset, rotated: A (s + m) + t = (A s + t) + A m
            for c in range(3):
                rotation = 3 * c * batch
                for b in range(batch):
                    out[v, c, b] += (blended[rotation + b] * moves[row, 0, b]
                                     + blended[rotation + batch + b] * moves[row, 1, b]
                                     + blended[rotation + 2 * batch + b] * moves[row, 2, b])


@compiled
def pose_one_body(rest, correctives, factors, moves, move_rows, transforms, bones, weights, out):
    """pose_block for one body, its arrays without the batch axis, adding the pose correctives
    itself: rest (n, 3) f32 (m); correctives (3 n, H), the correctives' regressor rows as float16
    bits (uint16; only where FLOAT16_IN_HARDWARE) or f32, and factors (H,) f32 (H = 0: none);
    moves (E, 3); transforms (J, 12); out (n, 3). (Loops of known length: 1.8x as fast as pose_block's at B = 1; the
    correctives' product here instead of in a scratch: 5% of the forward pass.)"""
    blended = np.empty(12, np.float32)
    for v in range(rest.shape[0]):
        blended[:] = 0.0
        for s in range(bones.shape[1]):
            weight = weights[v, s]
            if weight == 0.0:
                continue
            bone = transforms[bones[v, s]]
            for i in range(12):
                blended[i] += weight * bone[i]
        x, y, z = rest[v, 0], rest[v, 1], rest[v, 2]
        for k in range(factors.shape[0]):
            x += to_float32(correctives[3 * v, k]) * factors[k]
            y += to_float32(correctives[3 * v + 1, k]) * factors[k]
            z += to_float32(correctives[3 * v + 2, k]) * factors[k]
        row = move_rows[v]
        if row >= 0:
            x, y, z = x + moves[row, 0], y + moves[row, 1], z + moves[row, 2]
        for c in range(3):
            out[v, c] = blended[3 * c] * x + blended[3 * c + 1] * y + blended[3 * c + 2] * z + blended[9 + c]


@compiled
def forward_kinematics(rotations, rest, translation, parents, A, t, joints):
    """rotations (B, J, 3, 3), rest joints (B or 1, J, 3) (m), translation (B, 3) (m), parents
    (J,) i32, each before its children (root: -1) -> A (B, J, 3, 3), t (B, J, 3), joints (B, J, 3)
    written (the convention of humotion.body.skinning.skinning_transforms)."""
    for b in range(rotations.shape[0]):
        r = b if rest.shape[0] > 1 else 0
        for j in range(rotations.shape[1]):
            p = parents[j]
            for c in range(3):
                if p < 0:
                    joints[b, j, c] = rest[r, j, c] + translation[b, c]
                    for d in range(3):
                        A[b, j, c, d] = rotations[b, j, c, d]
                else:   # p_j = p_parent + A_parent (rest_j - rest_parent); A_j = A_parent R_j
                    joints[b, j, c] = joints[b, p, c] + (A[b, p, c, 0] * (rest[r, j, 0] - rest[r, p, 0])
                                                         + A[b, p, c, 1] * (rest[r, j, 1] - rest[r, p, 1])
                                                         + A[b, p, c, 2] * (rest[r, j, 2] - rest[r, p, 2]))
                    for d in range(3):
                        A[b, j, c, d] = (A[b, p, c, 0] * rotations[b, j, 0, d] + A[b, p, c, 1] * rotations[b, j, 1, d]
                                         + A[b, p, c, 2] * rotations[b, j, 2, d])
            for c in range(3):   # t_j = p_j - A_j rest_j
                t[b, j, c] = joints[b, j, c] - (A[b, j, c, 0] * rest[r, j, 0] + A[b, j, c, 1] * rest[r, j, 1]
                                                + A[b, j, c, 2] * rest[r, j, 2])


@compiled
def heights(rest, out):
    """rest (V, 3, B) vertex-major meshes -> out (B,) their vertical extents (max y - min y)."""
    if rest.shape[2] == 1:   # one body: in registers (2.2x as fast as the loop below)
        top = bottom = rest[0, 1, 0]
        for v in range(1, rest.shape[0]):
            top, bottom = max(top, rest[v, 1, 0]), min(bottom, rest[v, 1, 0])
        out[0] = top - bottom
        return
    top, bottom = rest[0, 1].copy(), rest[0, 1].copy()
    for v in range(1, rest.shape[0]):
        for b in range(rest.shape[2]):
            top[b] = max(top[b], rest[v, 1, b])
            bottom[b] = min(bottom[b], rest[v, 1, b])
    out[:] = top - bottom
