"""Learned retargeting between skeleton domains (specs/retargeting.md), with shipped weights.

    from humotion.retarget.learned import retarget_learned
    result = retarget_learned(cmu_motion, game_rig_skeleton)       # same frames and fps

The source is read as features of its domain (humotion.retarget.domains), resampled to the
networks' frame rate (30 fps), cut into windows of the training length (64 frames, one every
half window), each in the frame of its own first frame as in training, encoded into per-part
codes with its body's skeleton codes and decoded with the target body's skeleton codes
(humotion.retarget.networks); the windows are blended over their overlaps and the result
resampled back to the source's frames. A take with jumps of the pelvis
(humotion.retarget.data.pieces) goes through in pieces between them. The target's pelvis moves
as the decoded root motion says (velocity and height in hip heights, so scaled by the target's
legs), each window starting where the source's pelvis is, scaled by the ratio of hip heights
(as the classical retargeter scales the whole trajectory); so a long take does not drift.
Unmodelled target joints (fingers, twist bones, face) take their domain's mean rotation.
feet=True then keeps the source's foot contacts with the classical retargeter's leg IK
(humotion.retarget.classical), the usual post-process of learned retargeting; feet=False gives
the networks' output alone.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import torch

from humotion import rotations as rot
from humotion.assets import ASSETS
from humotion.motion import Motion
from humotion.retarget.classical import FOOT_POINTS, as_rig, check_finite, plant_feet, root_for
from humotion.retarget.contacts import foot_contacts
from humotion.retarget.data import pieces
from humotion.retarget.domains import Body, DomainSpec, domain_of, from_features, read_motion, to_features
from humotion.retarget.networks import RetargetNet, load_retarget_net
from humotion.retarget.rig import Rig
from humotion.skeleton import Skeleton, forward_kinematics

DEFAULT_WEIGHTS = ASSETS / "retarget" / "retarget_net.pt"


@lru_cache(maxsize=4)
def _cached(path: str) -> RetargetNet:
    return load_retarget_net(path)


def load_weights(weights: str | Path | RetargetNet | None = None) -> RetargetNet:
    """The networks from a weight file (default: the shipped ones), or weights itself when it is
    a RetargetNet. Files are read once per process."""
    if isinstance(weights, RetargetNet):
        return weights.eval()
    path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
    if not path.is_file():
        raise FileNotFoundError(f"no retargeter weights at {path} (train them: humotion train retarget)")
    return _cached(str(path.resolve()))


def _target_locals(spec: DomainSpec, fill: torch.Tensor, skeleton: Skeleton, rotations: torch.Tensor) -> torch.Tensor:
    """(T, J, 3, 3) local rotations of every joint of skeleton from the decoded (T, J_d, 3, 3)
    (pelvis world, others local); fill (len(spec.others), 4): the unmodelled joints' rotations."""
    index = spec.indices(skeleton)
    constant = rot.quat_identity(skeleton.num_joints)
    for name, q in zip(spec.others, fill):
        if name in skeleton.names:
            constant[skeleton.index(name)] = q
    local = rot.quat_to_matrix(constant).repeat(len(rotations), 1, 1, 1)
    local[:, index] = rotations
    parent = skeleton.parents[index[0]]
    if parent >= 0:  # joints above the pelvis (a floor bone) keep constant rotations: undo them
        above = forward_kinematics(local[:1], torch.zeros(1, 3), skeleton.offsets, skeleton.parents)[0][0, parent]
        local[:, index[0]] = above.T @ rotations[:, 0]
    return local


def _frames(motion: Motion, frames: int) -> Motion:
    """The motion cut or padded (last frame held) to `frames` frames."""
    extra = frames - len(motion)
    if extra <= 0:
        return motion[:frames]
    return Motion(motion.skeleton, torch.cat([motion.rotations, motion.rotations[-1:].expand(extra, -1, -1)]),
                  torch.cat([motion.root_positions, motion.root_positions[-1:].expand(extra, -1)]), motion.fps,
                  name=motion.name)


def _transfer(net: RetargetNet, source: str, source_body: Body, target: str, target_body: Body,
              rotations: torch.Tensor, pelvis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One window through the networks: source rotations (T, J_s, 3, 3) and pelvis (T, 3)
    (domains.read_motion) -> target rotations (T, J_t, 3, 3) and pelvis (T, 3), metres, the
    target's pelvis starting where the source's does, scaled by the ratio of hip heights."""
    features, root, yaw, origin = to_features(rotations, pelvis, source_body.facing,
                                              torch.tensor(source_body.hip_height), net.fps)
    features, root = net.normalizers[source].normalize(features, root)
    features, root = net.retarget(source, features[None], root[None], source_body.offsets[None],
                                  target, target_body.offsets[None])
    features, root = net.normalizers[target].denormalize(features[0], root[0])
    scale = target_body.hip_height / source_body.hip_height
    return from_features(features, root, yaw, origin * scale, target_body.hip_height, net.fps)


def _transfer_windows(net: RetargetNet, *bodies, rotations: torch.Tensor,
                      pelvis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """_transfer over a piece of any length: windows of the training length (net.config.window
    frames) every half window, each in its own frame as in training, blended with triangular
    weights over the overlaps (6D rotations averaged, then made rotations again)."""
    length, frames = net.config.window, len(rotations)
    if frames <= length:
        return _transfer(net, *bodies, rotations, pelvis)
    weight = torch.minimum(torch.arange(1, length + 1), torch.arange(length, 0, -1)).float()
    joints = bodies[3].offsets.shape[0]
    sixd, position, total = torch.zeros(frames, joints, 6), torch.zeros(frames, 3), torch.zeros(frames)
    for start in [*range(0, frames - length, length // 2), frames - length]:
        part = slice(start, start + length)
        turned, moved = _transfer(net, *bodies, rotations[part], pelvis[part])
        sixd[part] += weight[:, None, None] * rot.convert(turned, "matrix", "sixd")
        position[part] += weight[:, None] * moved
        total[part] += weight
    return rot.convert(sixd / total[:, None, None], "sixd", "matrix"), position / total[:, None]


@torch.no_grad()
def retarget_learned(source: Motion, target: Skeleton | Rig, weights: str | Path | RetargetNet | None = None, *,
                     source_rig: Rig | None = None, feet: bool = True) -> Motion:
    """The source motion on the target skeleton (same frames and fps) by the learned retargeter.

    target: a Skeleton or Rig of one of the weights' skeleton domains (the shipped weights: the
        31-joint CMU ASF skeleton and the 100/101-joint iClone game rig), any bone lengths.
    weights: a weight file or RetargetNet (default: the shipped weights).
    feet: keep the source's foot contacts with leg IK (module docstring).
    Raises ValueError for NaNs in the source (frame and joint named) and for a source or target
    skeleton of no domain of the weights.
    """
    check_finite(source)
    net = load_weights(weights)
    target_rig = as_rig(target, "target rig")
    source_spec = domain_of(source.skeleton, net.config.domains)
    target_spec = domain_of(target_rig.skeleton, net.config.domains)
    source_rig = source_rig or as_rig(source.skeleton, source.name or "source")
    source_body, target_body = Body.of(source_spec, source_rig), Body.of(target_spec, target_rig)
    motion = source.resample(net.fps)
    rotations, pelvis = read_motion(motion, source_spec)
    bodies = (source_spec.name, source_body, target_spec.name, target_body)
    outputs = [_transfer_windows(net, *bodies, rotations=rotations[start:end], pelvis=pelvis[start:end])
               for start, end in pieces(pelvis, net.fps)]
    rotations, pelvis = (torch.cat(x) for x in zip(*outputs))
    skeleton = target_rig.skeleton
    local = _target_locals(target_spec, net.normalizers[target_spec.name].other_rotations, skeleton, rotations)
    root_positions = root_for(local, skeleton, target_spec.indices(skeleton)[0], pelvis)
    result = Motion(skeleton, rot.matrix_to_quat(local), root_positions, net.fps, name=source.name)
    if result.fps != source.fps:
        result = _frames(result.resample(source.fps), len(source))
    if not feet:
        return result
    contacts = foot_contacts(source_rig.points(*source.world(), FOOT_POINTS), source.fps, source_rig.standing_height())
    local = plant_feet(rot.quat_to_matrix(result.rotations.double()), result.root_positions.double(), target_rig,
                        contacts, source.fps)
    return Motion(skeleton, rot.matrix_to_quat(local).float(), result.root_positions, source.fps, name=source.name)
