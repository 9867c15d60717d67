"""Skeleton: the joint tree every motion refers to, and forward kinematics on it.

Conventions (DESIGN.md): metres, right-handed, Y up, a character's rest facing is +Z, so its
left side is +X. A joint's rotation turns its children; its offset is its rest position in its
parent's frame. With every local rotation the identity, the skeleton stands in its rest pose.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field

import numpy as np
import torch

from humotion import rotations as rot


def _float_rows(values, what: str) -> torch.Tensor:
    """values (numpy array, nested lists or a tensor) as a float32 CPU tensor (n, 3)."""
    tensor = torch.as_tensor(np.asarray(values, dtype=np.float32) if not isinstance(values, torch.Tensor) else values)
    tensor = tensor.detach().to(device="cpu", dtype=torch.float32)
    if tensor.numel() % 3:
        raise ValueError(f"skeleton {what} have shape {tuple(tensor.shape)}, expected (n, 3)")
    return tensor.reshape(-1, 3)


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A joint tree.

    names: J unique joint names. parents: J parent indices, -1 for the root (joint 0), every
    parent listed before its children. offsets: (J, 3) float32 tensor, the rest offset of each
    joint from its parent, metres (the root's offset is its rest position). End sites are leaf
    points without rotation (finger tips, head top): end_site_parents (E,), end_site_offsets
    (E, 3) float32 tensor, end_site_names (E,). Offsets given as numpy arrays or lists are
    converted; float32, like Motion's tensors, keeps about 7 significant digits (a tenth of a
    micrometre on a 2 m figure).

    Skeletons compare and hash by identity (a skeleton read from a file is the key of its file's
    BVH style); compare names, parents and offsets (torch.equal) to tell whether two are alike.
    """

    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: torch.Tensor
    end_site_parents: tuple[int, ...] = ()
    end_site_offsets: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    end_site_names: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "parents", tuple(int(p) for p in self.parents))
        object.__setattr__(self, "offsets", _float_rows(self.offsets, "offsets"))
        object.__setattr__(self, "end_site_parents", tuple(int(p) for p in self.end_site_parents))
        object.__setattr__(self, "end_site_offsets", _float_rows(self.end_site_offsets, "end site offsets"))
        if not self.end_site_names:
            object.__setattr__(self, "end_site_names", tuple(f"{self.names[p]}_end" for p in self.end_site_parents))
        object.__setattr__(self, "end_site_names", tuple(self.end_site_names))
        self._validate()

    def _validate(self) -> None:
        n = len(self.names)
        if n == 0:
            raise ValueError("a skeleton needs at least one joint")
        if len(self.parents) != n or len(self.offsets) != n:
            raise ValueError(f"skeleton has {n} names, {len(self.parents)} parents and {len(self.offsets)} offsets")
        if len(set(self.names)) != n:
            dup = sorted({x for x in self.names if self.names.count(x) > 1})
            raise ValueError(f"duplicate joint names: {dup}")
        if self.parents[0] != -1 or any(not (0 <= p < j) for j, p in enumerate(self.parents) if j > 0):
            raise ValueError("parents must be -1 for joint 0 and an earlier joint for every other joint")
        if not torch.isfinite(self.offsets).all() or not torch.isfinite(self.end_site_offsets).all():
            raise ValueError("skeleton offsets must be finite")
        if not (len(self.end_site_parents) == len(self.end_site_offsets) == len(self.end_site_names)):
            raise ValueError("end site parents, offsets and names differ in length")
        if any(not (0 <= p < n) for p in self.end_site_parents):
            raise ValueError("end site parent out of range")

    # -- lookup ---------------------------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of a joint by name; KeyError naming the joint and the skeleton's joints."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r} in skeleton (joints: {', '.join(self.names)})") from None

    def children(self, joint: int) -> list[int]:
        return [j for j, p in enumerate(self.parents) if p == joint]

    def depth(self) -> torch.Tensor:
        """(J,) int64 number of ancestors of each joint."""
        d = [0] * self.num_joints
        for j in range(1, self.num_joints):
            d[j] = d[self.parents[j]] + 1
        return torch.tensor(d, dtype=torch.int64)

    # -- geometry -------------------------------------------------------------------------
    def rest_positions(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(J, 3) world joint positions in the rest pose, metres, in dtype (summed in float64
        either way: float64 for rest-pose geometry that must not round twice)."""
        return self._rest64()[0].to(dtype)

    def rest_end_site_positions(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(E, 3) world end-site positions in the rest pose, metres, in dtype (as rest_positions)."""
        return self._rest64()[1].to(dtype)

    def rest_points(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(J + E, 3) world positions in the rest pose of the joints, then the end sites, metres,
        in dtype (as rest_positions)."""
        return torch.cat(self._rest64()).to(dtype)

    def height(self) -> float:
        """Vertical extent of the rest pose (joints and end sites), metres."""
        pts = torch.cat(self._rest64())
        return float(pts[:, 1].max() - pts[:, 1].min())

    def _rest64(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest positions of the joints (J, 3) and end sites (E, 3), float64: summed as Python
        floats (a few times faster than a tensor operation per joint), so a chain thousands of
        joints deep keeps float32's precision."""
        rows = self.offsets.double().tolist()
        pos: list[list[float]] = []
        for j, p in enumerate(self.parents):
            pos.append([a + b for a, b in zip(rows[j], pos[p])] if p >= 0 else rows[j])
        ends = [[a + b for a, b in zip(o, pos[p])]
                for p, o in zip(self.end_site_parents, self.end_site_offsets.double().tolist())]
        return torch.tensor(pos, dtype=torch.float64), torch.tensor(ends, dtype=torch.float64).reshape(-1, 3)

    def scaled(self, factor: float) -> "Skeleton":
        """The same tree with every offset multiplied by factor."""
        return Skeleton(self.names, self.parents, self.offsets * factor, self.end_site_parents,
                        self.end_site_offsets * factor, self.end_site_names)

    # -- symmetry -------------------------------------------------------------------------
    def mirror_indices(self) -> torch.Tensor:
        """(J,) int64 index of each joint's left/right counterpart (itself for central joints).

        Recognises the usual spellings: left/right in any case, L_/R_ or _L/_R separated
        markers, and one-letter prefixes as in CMU ASF (lfemur/rfemur) or lShldr/rShldr.
        """
        return counterpart_indices(self.names)

    def mirror_end_site_indices(self) -> torch.Tensor:
        """(E,) int64 index of each end site's left/right counterpart."""
        return counterpart_indices(self.end_site_names)

    def mirrored(self) -> "Skeleton":
        """The skeleton reflected through the X = 0 plane, left and right names kept in place."""
        m, e = self.mirror_indices(), self.mirror_end_site_indices()
        flip = torch.tensor([-1.0, 1.0, 1.0])
        return Skeleton(self.names, self.parents, self.offsets[m] * flip, self.end_site_parents,
                        self.end_site_offsets[e] * flip, self.end_site_names)

    def __repr__(self) -> str:
        return f"Skeleton({self.num_joints} joints, root={self.names[0]!r}, height={self.height():.2f} m)"


_SIDE_WORDS = {"left": "right", "right": "left", "Left": "Right", "Right": "Left", "LEFT": "RIGHT", "RIGHT": "LEFT"}


def _side_swaps(name: str):
    """Candidate names of the other side's joint (some may not exist)."""
    yield re.sub(r"left|right|Left|Right|LEFT|RIGHT", lambda m: _SIDE_WORDS[m.group()], name)
    for a, b in (("L", "R"), ("R", "L"), ("l", "r"), ("r", "l")):
        yield re.sub(rf"(^|[_.\-]){a}(?=$|[_.\-])", rf"\g<1>{b}", name)
        if name.startswith(a):
            yield b + name[1:]


def counterpart_indices(names) -> torch.Tensor:
    """(N,) int64 index of each name's left/right counterpart among names (itself when it has
    none), for the spellings of :meth:`Skeleton.mirror_indices`."""
    index = {n: i for i, n in enumerate(names)}
    result = list(range(len(names)))
    for i, name in enumerate(names):
        for candidate in _side_swaps(name):
            if candidate != name and candidate in index:
                result[i] = index[candidate]
                break
    return torch.tensor(result, dtype=torch.int64)


def local_rotations(world_rotations: torch.Tensor, parents) -> torch.Tensor:
    """(..., J, 3, 3) rotations of each joint relative to its parent (joint 0: its world
    rotation) from world rotations (..., J, 3, 3): what :func:`forward_kinematics` undoes."""
    parent = world_rotations[..., [max(p, 0) for p in parents], :, :]
    local = parent.transpose(-1, -2) @ world_rotations
    return torch.cat([world_rotations[..., :1, :, :], local[..., 1:, :, :]], dim=-3)


def forward_kinematics(local_rotations, root_positions, offsets, parents):
    """World joint rotations and positions from local rotations.

    local_rotations: (..., J, 4) wxyz quaternions or (..., J, 3, 3) matrices.
    root_positions: (..., 3) world position of joint 0, metres.
    offsets: (J, 3) or (..., J, 3) offsets of each joint in its parent's frame, metres
        (the root's entry is ignored: root_positions places it).
    parents: sequence of J parent indices (-1 for the root).
    Inputs may be numpy arrays or torch tensors. Returns (world_rotations (..., J, 3, 3),
    world_positions (..., J, 3)) as torch tensors in local_rotations' float dtype (float32 for
    integers). Differentiable.
    """
    local = torch.as_tensor(local_rotations)
    dtype = local.dtype if local.is_floating_point() else torch.float32
    local = local.to(dtype)
    if local.shape[-1] == 4:
        local = rot.quat_to_matrix(local)
    root = torch.as_tensor(root_positions, dtype=dtype)
    off = torch.as_tensor(offsets, dtype=dtype)
    if local.shape[-3] != len(parents) or off.shape[-2] != len(parents):
        raise ValueError(f"forward_kinematics: {len(parents)} parents but rotations {tuple(local.shape)} and offsets {tuple(off.shape)}")
    world_r: list[torch.Tensor] = []
    world_p: list[torch.Tensor] = []
    for j, p in enumerate(parents):
        if p < 0:
            world_r.append(local[..., j, :, :])
            world_p.append(root.expand(local.shape[:-3] + (3,)))
        else:
            world_r.append(world_r[p] @ local[..., j, :, :])
            world_p.append(world_p[p] + (world_r[p] @ off[..., j, :, None])[..., 0])
    return torch.stack(world_r, dim=-3), torch.stack(world_p, dim=-2)


def depth_levels(parents: tuple[int, ...]) -> tuple[torch.Tensor, list[int], list[torch.Tensor], torch.Tensor]:
    """The rig's joints by depth below the root, for :func:`forward_kinematics_by_level` (cached
    per rig): (order (J,) the joints depth by depth, sizes: the number of joints at each depth,
    per depth after the root's the joints' parents as indices into the depth above (in order),
    inverse (J,) each joint's place in order). While torch traces (an ONNX export), tensors are
    made afresh: ones made then are placeholders and must not reach the cache."""
    if torch.compiler.is_compiling():
        return _depth_levels.__wrapped__(parents)
    return _depth_levels(parents)


@functools.lru_cache(maxsize=16)
def _depth_levels(parents: tuple[int, ...]) -> tuple[torch.Tensor, list[int], list[torch.Tensor], torch.Tensor]:
    depth: list[int] = []
    for p in parents:
        depth.append(0 if p < 0 else depth[p] + 1)
    order = sorted(range(len(parents)), key=lambda j: depth[j])  # stable: by depth, then index
    sizes = [depth.count(d) for d in range(max(depth) + 1)]
    place = {j: i for i, j in enumerate(order)}
    starts = [sum(sizes[:d]) for d in range(len(sizes))]
    above = [torch.tensor([place[parents[j]] - starts[d - 1] for j in order[starts[d]:starts[d] + sizes[d]]])
             for d in range(1, len(sizes))]
    return torch.tensor(order), sizes, above, torch.tensor([place[j] for j in range(len(parents))])


def forward_kinematics_by_level(local: torch.Tensor, root: torch.Tensor, offsets: torch.Tensor, parents):
    """:func:`forward_kinematics` for a deep rig, one batched product per depth level
    (17 for the 76-joint body rig) instead of a step per joint: far fewer tensor operations,
    which is most of a batch-1 forward pass. local (..., J, 3, 3), root (..., 3),
    offsets (..., J, 3); returns world rotations (..., J, 3, 3) and positions (..., J, 3);
    differentiable."""
    shape = local.shape[:-3]
    J = local.shape[-3]
    offsets = offsets.expand(shape + (J, 3))
    # local transforms [R_j | o_j] (the root's offset is its world position)
    top = torch.cat([local, torch.cat([root[..., None, :], offsets[..., 1:, :]], dim=-2)[..., None]], dim=-1)
    bottom = local.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(shape + (J, 1, 4))
    transforms = torch.cat([top, bottom], dim=-2)  # (..., J, 4, 4)
    order, sizes, above, inverse = depth_levels(tuple(int(p) for p in parents))
    levels = transforms.index_select(-3, order.to(local.device)).split(sizes, dim=-3)
    world = [levels[0][..., :3, :]]  # [(..., joints at the depth, 3, 4), ...]
    for transform, parent in zip(levels[1:], above):
        world.append(world[-1].index_select(-3, parent.to(local.device)) @ transform)
    world = torch.cat(world, dim=-3).index_select(-3, inverse.to(local.device))
    return world[..., :3], world[..., 3]
