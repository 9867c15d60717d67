"""Weight matrices kept as float16 and read by compiled loops (numba), for products with one
vector: the body model's big matrices (the shape and expression decoders' output layers, the
pose correctives' regressor) hold float16 numbers exactly, since the shipped weights are stored
as float16 (:func:`humotion.model_files.save_model_file`), so a float16 copy gives the same
result from half the bytes. At batch 1 such a product only streams its matrix from memory, and
this one takes about half the time of torch's float32 product (0.22 against 0.42 ms for the
full-resolution shape decoder's 41,154 x 64 on one thread); up to batch 4 it is still faster
(0.61 against 0.89 ms), beyond that torch's is.

Imported by :mod:`humotion.body.cpu_posing` when it compiles its kernels (this module needs
numba at import).
"""

from __future__ import annotations

import numpy as np
import torch
from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def half_to_float(typing_context, bits):
    """float32 of the float16 whose bits (uint16) are given, in compiled code (numba has no
    float16 type; LLVM turns this into x86's F16C conversion, eight or sixteen at a time)."""
    signature = types.float32(types.uint16)

    def codegen(context, builder, _signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return signature, codegen


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


def half_bits(weight: torch.Tensor) -> np.ndarray | None:
    """weight (R, K) float32 as the bits of float16 numbers, (R, K) uint16, where float16 holds
    every number exactly (None where it does not: such a matrix is kept in float32)."""
    half = weight.detach().half()
    if not torch.equal(half.float(), weight.detach()):
        return None
    return half.numpy().view(np.uint16)
