"""Rotation forms used across humotion, converted through roma.

humotion stores rotations as unit quaternions in (w, x, y, z) order, shape (..., 4).
roma works in (x, y, z, w); this module is the only place that reorders, so the rest of
the package never touches quaternion components or Euler algebra directly.

Forms understood by :func:`convert`:

=========  =============  ==================================================================
form       shape          meaning
=========  =============  ==================================================================
quat       (..., 4)       unit quaternion (w, x, y, z)
matrix     (..., 3, 3)    rotation matrix acting on column vectors
rotvec     (..., 3)       axis * angle (radians), also called exponential map
sixd       (..., 6)       first two columns of the matrix, (r00, r10, r20, r01, r11, r21)
=========  =============  ==================================================================

Euler angles are converted with :func:`euler_to_quat` / :func:`quat_to_euler`, which take
roma's convention strings: upper case is intrinsic, lower case extrinsic. A BVH channel list
"Zrotation Yrotation Xrotation" is the intrinsic convention "ZYX" (R = Rz @ Ry @ Rx).
"""

from __future__ import annotations

import roma
import torch

FORMS = ("quat", "matrix", "rotvec", "sixd")


def _wxyz(q_xyzw: torch.Tensor) -> torch.Tensor:
    return roma.quat_xyzw_to_wxyz(q_xyzw)


def _xyzw(q_wxyz: torch.Tensor) -> torch.Tensor:
    return roma.quat_wxyz_to_xyzw(q_wxyz)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz unit quaternions -> (..., 3, 3) rotation matrices."""
    return roma.unitquat_to_rotmat(_xyzw(q))


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) wxyz unit quaternions with w >= 0."""
    q = _wxyz(roma.rotmat_to_unitquat(m))
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)


def _markley(r: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) the symmetric matrix 4 q q^T of rotation matrices r (..., 3, 3), q their unit
    quaternions wxyz: linear in r (Markley 2008, as roma.rotmat_to_unitquat)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = (row.unbind(-1) for row in r.unbind(-2))
    rows = [(1 + r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01),
            (r21 - r12, 1 + r00 - r11 - r22, r01 + r10, r02 + r20),
            (r02 - r20, r01 + r10, 1 - r00 + r11 - r22, r12 + r21),
            (r10 - r01, r02 + r20, r12 + r21, 1 - r00 - r11 + r22)]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def _markley_affine() -> tuple[torch.Tensor, torch.Tensor]:
    """_markley as m.flatten(-2) @ weight (9, 20) + bias (20,): its 16 entries, then its diagonal."""
    k = _markley(torch.cat([torch.zeros(1, 9), torch.eye(9)]).view(10, 3, 3))      # at 0, then at each unit matrix
    k = torch.cat([k.flatten(-2), k.diagonal(dim1=-2, dim2=-1)], -1)               # (10, 20)
    return k[1:] - k[0], k[0]


_MARKLEY_WEIGHT, _MARKLEY_BIAS = _markley_affine()


def matrix_to_quat_in_one_product(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) wxyz unit quaternions with w >= 0: the maths of
    matrix_to_quat (roma's: the row of 4 q q^T with the largest diagonal entry, normalised) as one
    matrix product, so a graph exported to ONNX has a few nodes instead of about 80 (used by the
    sparse tracker's per-frame function)."""
    x = m.flatten(-2) @ _MARKLEY_WEIGHT.to(m) + _MARKLEY_BIAS.to(m)              # (..., 20)
    rows, diagonal = x[..., :16].unflatten(-1, (4, 4)), x[..., 16:]
    best = diagonal.argmax(-1)[..., None, None].expand(*diagonal.shape[:-1], 1, 4)
    q = torch.gather(rows, -2, best)[..., 0, :]
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (..., 4) wxyz quaternions (rotation b first, then a)."""
    return _wxyz(roma.quat_product(_xyzw(a), _xyzw(b)))


def quat_inv(q: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4) wxyz unit quaternions."""
    return _wxyz(roma.quat_conjugation(_xyzw(q)))


def quat_apply(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate (..., 3) vectors by (..., 4) wxyz unit quaternions."""
    return roma.quat_action(_xyzw(q), v, is_normalized=True)


def quat_identity(*shape: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Identity quaternions of shape (*shape, 4)."""
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def quat_slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Shortest-arc spherical interpolation with a separate weight per element.

    q0, q1: (..., 4) wxyz; t: (...) in [0, 1], broadcastable against q0[..., 0].
    Returns (..., 4): q0 at t = 0, q1 (or -q1) at t = 1.
    """
    delta = roma.unitquat_to_rotvec(roma.quat_product(roma.quat_conjugation(_xyzw(q0)), _xyzw(q1)))
    step = roma.rotvec_to_unitquat(delta * t.unsqueeze(-1))
    return _wxyz(roma.quat_product(_xyzw(q0), step))


def euler_to_quat(convention: str, angles: torch.Tensor, degrees: bool = True) -> torch.Tensor:
    """Euler angles (..., len(convention)) -> (..., 4) wxyz quaternions with w >= 0 (roma convention)."""
    q = _wxyz(roma.euler_to_unitquat(convention, angles, degrees=degrees))
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)


def quat_to_euler(convention: str, q: torch.Tensor, degrees: bool = True) -> torch.Tensor:
    """(..., 4) wxyz quaternions -> Euler angles (..., 3) in the roma convention string."""
    return roma.rotmat_to_euler(convention, quat_to_matrix(q), degrees=degrees)


def convert(rotations: torch.Tensor, source: str, target: str) -> torch.Tensor:
    """Rotations in form `source` -> the same rotations in form `target`, both from :data:`FORMS`:
    quat (..., 4) wxyz, matrix (..., 3, 3), rotvec (..., 3) radians, sixd (..., 6); the leading
    dimensions (...) and the dtype are kept (see the module docstring)."""
    for form in (source, target):
        if form not in FORMS:
            raise ValueError(f"unknown rotation form {form!r}; expected one of {FORMS}")
    if source == target:
        return rotations
    matrix = {
        "quat": quat_to_matrix,
        "matrix": lambda r: r,
        "rotvec": roma.rotvec_to_rotmat,
        "sixd": lambda r: roma.special_gramschmidt(r.unflatten(-1, (2, 3)).transpose(-1, -2)),
    }[source](rotations)
    return {
        "quat": matrix_to_quat,
        "matrix": lambda m: m,
        "rotvec": roma.rotmat_to_rotvec,
        "sixd": lambda m: m[..., :, :2].transpose(-1, -2).flatten(-2),
    }[target](matrix)


def rotation_matrix_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Smallest rotation taking directions a to b, both (..., 3) (need not be unit), as (..., 3, 3)
    matrices: I + K + K^2 / (1 + a.b) with K the cross-product matrix of a x b, no round trip
    through another form (cheap enough for per-frame use). Opposite vectors: as rotation_between."""
    a = torch.nn.functional.normalize(a, dim=-1)
    b = torch.nn.functional.normalize(b, dim=-1)
    cos = (a * b).sum(-1)
    if bool((cos < -1 + 1e-6).any()):
        return quat_to_matrix(rotation_between(a, b))
    x, y, z = torch.linalg.cross(a, b).unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(a.shape[:-1] + (3, 3))
    return torch.eye(3, dtype=a.dtype) + k + k @ k / (1 + cos)[..., None, None]


def rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Smallest rotation taking directions a to b, both (..., 3) (need not be unit).

    Returns (..., 4) wxyz. Opposite vectors give a half turn about an axis orthogonal to a.
    """
    a = torch.nn.functional.normalize(a, dim=-1)
    b = torch.nn.functional.normalize(b, dim=-1)
    axis = torch.linalg.cross(a, b)
    sin = axis.norm(dim=-1, keepdim=True)
    cos = (a * b).sum(-1, keepdim=True)
    # Fallback axis for opposite vectors: any vector orthogonal to a.
    helper = torch.where(a[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0], dtype=a.dtype), torch.tensor([0, 1.0, 0], dtype=a.dtype))
    ortho = torch.nn.functional.normalize(torch.linalg.cross(a, helper), dim=-1)
    axis = torch.where(sin > 1e-8, axis / sin.clamp_min(1e-12), ortho)
    return matrix_to_quat(roma.rotvec_to_rotmat(axis * torch.atan2(sin, cos)))
