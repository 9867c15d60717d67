"""Compiled (numba) building blocks shared by humotion's compiled loops (the body model's CPU
path, the sparse tracker's solver, the capture refinement's energy): the :func:`compiled`
decorator and small rotation helpers, functions of numpy arrays, float64."""

from __future__ import annotations

from typing import Callable

from numba import njit


def compiled(function: Callable) -> Callable:
    """function compiled by numba (no Python objects, fast math, no bounds checks, the GIL
    released), its machine code cached on disk next to its module or in numba's user cache
    directory; where neither can be written (a read-only install without a home directory),
    compiled afresh in each process instead of failing."""
    options = dict(fastmath=True, boundscheck=False, nogil=True)
    try:
        return njit(cache=True, **options)(function)
    except RuntimeError:   # numba: "cannot cache function ...: no locator available for file ..."
        return njit(**options)(function)


@compiled
def rodrigues(v, s, c, out):
    """out (3, 3) = I + s [v]x + c [v]x^2 = (1 - c |v|^2) I + s [v]x + c v v^T for v (3,),
    written out (numba builds nested-list arrays slowly). With s = sin a / a and
    c = (1 - cos a) / a^2, a = |v|, it is the rotation exp([v]x) (Rodrigues' formula)."""
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    for i in range(3):
        for j in range(3):
            out[i, j] = c * v[i] * v[j]
        out[i, i] += 1.0 - c * vv
    out[0, 1] -= s * v[2]
    out[0, 2] += s * v[1]
    out[1, 0] += s * v[2]
    out[1, 2] -= s * v[0]
    out[2, 0] -= s * v[1]
    out[2, 1] += s * v[0]
