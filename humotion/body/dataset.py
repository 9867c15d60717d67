"""Registered training meshes for the learned body model, made from Anny and real mocap poses.

    python -m humotion.body.dataset --out runs/body_data                 # 200 shapes x 8 poses
    python -m humotion.body.dataset --out /tmp/tiny --shapes 4 --poses-per-shape 2

    data = load_split("runs/body_data", "full", "train")     # vertices (M, V, 3), shape_id, rotations, ...
    model = load_model_file("runs/body_data", "full")        # faces, rest shapes, skinning weights, masks

What a run makes (every step deterministic in --seed):

1. Shapes: Anny's phenotype sampler fitted to WHO statistics (ages 4-90, both sexes, thin to
   heavy; :func:`humotion.body.anny_source.sample_phenotypes`), with height, mass and BMI.
2. Poses: frames of the CMU mocap under ../shared/data/mocap, mapped onto humotion's 22-joint
   canonical body (:func:`humotion.canonical.to_canonical`), heading removed, then retargeted onto
   Anny's 76-joint rig (:func:`retarget`): each mapped rig bone gets the canonical joint's world
   rotation after a rest alignment that turns Anny's A-pose bones onto the mocap's T-pose bone
   directions, so posed bone directions match the mocap's exactly. Fingers get random curls and
   the eyes a random gaze; twist and in-between spine/neck bones follow their parents.
3. Expressions: about half the meshes get 1-4 of Anny's 52 ARKit-style facial actions.
4. Meshes: Anny's dual-quaternion skinning (which plain LBS cannot reproduce, so pose correctives
   have something to learn) on two topologies sharing the skeleton: "full" (13,718 vertices) and
   "low" (1,229). Posed meshes stand on the floor (lowest vertex at y = 0), pelvis above the origin.
5. Splits: held-out shapes x held-out poses (poses of held-out CMU subjects, the split of
   MotionCollection.split() that humotion's training uses): train / test_shapes / test_poses /
   test_both.

Folder layout (``np.load`` them without pickle; strings are unicode arrays):

- manifest.json: counts, seed, command, versions, timings, the LBS-vs-DQS gap, licences.
- shapes.npz: per shape: phenotypes (N, 6) + phenotype_names, age_years, height, mass, bmi,
  waist, volume, held_out (bool).
- poses.npz: per pose (one per mesh, pose_id = mesh_id): clip, frame, subject, held_out,
  canonical_rotations (P, 22, 4) (heading removed), finger_curl (P, 2, 5), gaze (P, 2) radians.
- {full,low}/model.npz: faces (F, 3) int32, joint_names, parents, rest_vertices (N, V, 3) and
  rest_joints (N, J, 3) per shape (neutral expression, Anny's origin), skin_weights (V, J)
  (Anny's LBS weights), expression_basis (52, V, 3) + facial_action_names, part (V,) labels +
  part_names, region_body / region_face / region_hands (V,) bool.
- {full,low}/{split}.npz: per mesh: vertices (M, V, 3) float32 metres, mesh_id, shape_id,
  pose_id, rotations (M, J, 4) wxyz, translation (M, 3), joints (M, J, 3) posed joint centres,
  expression (M, 52), lbs_gap_mm (M,) (full only: mean distance of plain LBS from the DQS mesh).

Pose parameters: ``rotations`` are each joint's rest-relative rotation expressed in world-aligned
rest axes (SMPL-style): world rotation A_j = A_parent(j) @ R_j, posed joint
p_j = p_parent + A_parent (rest_j - rest_parent), root p_0 = rest_0 + translation, skinning
transform x -> A_j (x - rest_j) + p_j. :func:`skinning_transforms` and
:func:`linear_blend_skinning` implement it; vertices = DQS of (rest_vertices + expression offsets)
under those transforms. Expression offsets: ``expression @ expression_basis`` (a rest-pose,
neutral-head-pose offset: the expressive rest mesh minus the neutral one).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import click
import numpy as np
import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.canonical import END_SITES, JOINTS, canonical_skeleton, to_canonical
from humotion.skeleton import forward_kinematics

log = logging.getLogger("humotion.body.dataset")

DEFAULT_MOCAP = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mocap"
EXCLUDED_SOURCES = ("hdm05_jointlearning", "cmu_iclone_ccskeleton")
"""Mocap sources not used for poses: HDM05 is evaluation-only (CC BY-SA); the iClone set holds
game-rig copies of CMU takes whose zero pose is no T-pose."""

SPLITS = ("train", "test_shapes", "test_poses", "test_both")
"""Mesh splits by (shape held out, pose held out): (no, no), (yes, no), (no, yes), (yes, yes)."""

RESOLUTIONS = ("full", "low")
FORMAT_VERSION = 1
LICENCE = ("Meshes generated with Anny (NAVER, https://github.com/naver/anny): code Apache-2.0, "
           "body model assets derived from MakeHuman, CC0. Poses from the CMU Graphics Lab Motion "
           "Capture Database (mocap.cs.cmu.edu), funded by NSF EIA-0196217.")

# -- the rig mapping ---------------------------------------------------------------------------

CANONICAL_TO_RIG = {
    "pelvis": "root", "spine1": "spine04", "spine2": "spine02", "spine3": "spine01", "neck": "neck01", "head": "head",
    **{f"{side}_{joint}": f"{bone}.{s}" for side, s in (("left", "L"), ("right", "R")) for joint, bone in (
        ("hip", "upperleg01"), ("knee", "lowerleg01"), ("ankle", "foot"), ("collar", "clavicle"),
        ("shoulder", "upperarm01"), ("elbow", "lowerarm01"), ("wrist", "wrist"))},
}
"""Canonical joint -> Anny bone it drives. The canonical feet (toe bend) have no Anny bone; Anny's
twist bones (upperleg02, lowerleg02, upperarm02, lowerarm02), spine05/03, shoulder01, neck02/03
follow their parents, so each mapped bone's aim point below moves rigidly with it."""

AIMS = {
    "spine1": ("spine02", "spine2"), "spine2": ("spine01", "spine3"), "spine3": ("neck01", "neck"),
    "neck": ("head", "head"), "head": ("head_top", "head_top"),
    **{f"{side}_{joint}": (rig.format(s=s), canon.format(side=side)) for side, s in (("left", "L"), ("right", "R"))
       for joint, rig, canon in (
           ("hip", "lowerleg01.{s}", "{side}_knee"), ("knee", "foot.{s}", "{side}_ankle"),
           ("ankle", "toe_tip.{s}", "{side}_toe"), ("collar", "upperarm01.{s}", "{side}_shoulder"),
           ("shoulder", "lowerarm01.{s}", "{side}_elbow"), ("elbow", "wrist.{s}", "{side}_wrist"),
           ("wrist", "finger3-1.{s}", "{side}_hand"))},
}
"""Canonical joint -> (rig point, canonical point) whose direction from the joint defines the
bone's rest alignment. Rig points are bone heads or the extra points of :data:`RIG_POINTS`;
canonical points are joints or end sites (head_top, hands at the knuckles, toe tips)."""

RIG_POINTS = {"head_top": "head", "toe_tip.L": "foot.L", "toe_tip.R": "foot.R"}
"""Rig points that are not joints -> the bone carrying them (found on the rest mesh)."""

CANONICAL_POINTS = JOINTS + END_SITES
_TEMPLATE = canonical_skeleton()
_TEMPLATE_POINTS = np.concatenate([_TEMPLATE.rest_positions(), _TEMPLATE.rest_end_site_positions()])

FINGER_MAX_DEGREES = {1: (20.0, 35.0, 45.0), 2: (75.0, 95.0, 65.0), 3: (75.0, 95.0, 65.0),
                      4: (75.0, 95.0, 65.0), 5: (75.0, 95.0, 65.0)}
"""Largest flexion of each finger's three bones (finger<k>-1..3; 1 is the thumb) at curl 1."""

GAP_JOINTS = {"shoulders": "upperarm01", "elbows": "lowerarm01", "wrists": "wrist", "hips": "upperleg01",
              "knees": "lowerleg01"}
"""Where the LBS-vs-DQS gap is also reported: the blend zone of these joints (both sides)."""


def blend_zones(weights: np.ndarray, names, parents, threshold: float = 0.05) -> dict[str, np.ndarray]:
    """(V,) bool per GAP_JOINTS region: vertices skinned to both sides of the joint (the weight of
    the joint's subtree, over both body sides, between threshold and 1 - threshold), where linear
    blend skinning and dual quaternions differ most."""
    names, parents = list(names), list(parents)
    zones = {}
    for region, bone in GAP_JOINTS.items():
        zone = np.zeros(len(weights), dtype=bool)
        for s in ("L", "R"):
            subtree = {names.index(f"{bone}.{s}")}
            for j, p in enumerate(parents):
                if p in subtree:
                    subtree.add(j)
            share = weights[:, sorted(subtree)].sum(1)
            zone |= (share > threshold) & (share < 1 - threshold)
        zones[region] = zone
    return zones


# -- kinematics and skinning (pure; also what the trained model uses) --------------------------

def skinning_transforms(rest_joints: np.ndarray, parents, rotations: np.ndarray, translation: np.ndarray):
    """Bone transforms of the pose convention above.

    rest_joints (J, 3) or (K, J, 3); rotations (K, J, 3, 3) or (K, J, 4) wxyz; translation (K, 3).
    Returns (A (K, J, 3, 3), t (K, J, 3), posed joints (K, J, 3)), x -> A x + t per bone, float64.
    """
    rotations = np.array(rotations, dtype=np.float64)
    if rotations.shape[-1] == 4:
        rotations = rot.quat_to_matrix(torch.as_tensor(rotations)).numpy()
    rest = np.broadcast_to(np.asarray(rest_joints, dtype=np.float64), rotations.shape[:-2] + (3,))
    parents = list(parents)
    offsets = rest - rest[..., [max(p, 0) for p in parents], :]
    root = rest[..., 0, :] + np.asarray(translation, dtype=np.float64)
    A, joints = forward_kinematics(rotations, root, offsets, parents)
    t = joints - np.einsum("...ij,...j->...i", A, rest)
    return A, t, joints


def linear_blend_skinning(vertices: np.ndarray, weights: np.ndarray, A: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Plain LBS: vertices (K, V, 3) or (V, 3), weights (V, J), transforms A (K, J, 3, 3), t (K, J, 3)
    -> (K, V, 3)."""
    vertices = np.broadcast_to(vertices, (A.shape[0],) + np.shape(vertices)[-2:])
    blend_A = np.einsum("vj,kjab->kvab", weights, A)
    blend_t = np.einsum("vj,kja->kva", weights, t)
    return np.einsum("kvab,kvb->kva", blend_A, vertices) + blend_t


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) smallest rotations taking directions a onto b (both (..., 3))."""
    return rot.quat_to_matrix(rot.rotation_between(torch.as_tensor(a), torch.as_tensor(b))).numpy()


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by angle (...) radians about unit axis (..., 3)."""
    return rot.convert(torch.as_tensor(axis * np.asarray(angle)[..., None]), "rotvec", "matrix").numpy()


def retarget(world_rotations: np.ndarray, canonical_rest: np.ndarray, rig_rest: dict[str, np.ndarray],
             names, parents, extra: np.ndarray | None = None) -> np.ndarray:
    """Canonical poses onto the rig: local rotations (P, J, 3, 3) in the convention above.

    world_rotations (P, 22, 3, 3): canonical joints' world rotations (identity = the canonical
    T-pose). canonical_rest (P, 27, 3): canonical rest points (:data:`CANONICAL_POINTS`) of each
    pose's source skeleton. rig_rest: rest position (3,) of every rig joint and of the extra
    points of :data:`RIG_POINTS`. extra (P, J, 3, 3): local rotations of unmapped bones (fingers,
    eyes), identity when None.

    Rest alignment S_j (the rig's A-pose -> the mocap's T-pose): the root's is the identity (both
    face +Z); a mapped bone adds to its parent's the smallest turn taking its aim direction onto
    the canonical one; an unmapped bone keeps its parent's. A mapped bone's world rotation is then
    G_c S_j (G_c: its canonical joint's), an unmapped one's its parent's times its extra rotation.
    """
    names, parents = list(names), list(parents)
    count = len(world_rotations)
    eye = np.broadcast_to(np.eye(3), (count, 3, 3))
    driver = {names.index(bone): JOINTS.index(joint) for joint, bone in CANONICAL_TO_RIG.items()}
    S = np.empty((count, len(names), 3, 3))
    A = np.empty((count, len(names), 3, 3))
    for j, p in enumerate(parents):
        S_parent = S[:, p] if p >= 0 else eye
        A_parent = A[:, p] if p >= 0 else eye
        if j not in driver:
            S[:, j] = S_parent
            A[:, j] = A_parent if extra is None else A_parent @ extra[:, j]
            continue
        joint = JOINTS[driver[j]]
        if joint in AIMS:
            rig_aim, canon_aim = AIMS[joint]
            a = S_parent @ (rig_rest[rig_aim] - rig_rest[names[j]])
            S[:, j] = _turn(a, _canonical_aim(canonical_rest, joint, canon_aim)) @ S_parent
        else:
            S[:, j] = S_parent
        A[:, j] = world_rotations[:, driver[j]] @ S[:, j]
    A_parent = np.concatenate([eye[:, None], A[:, [max(p, 0) for p in parents[1:]]]], axis=1)
    local = np.swapaxes(A_parent, -1, -2) @ A
    local[:, 0] = A[:, 0]
    return local


def _canonical_aim(canonical_rest: np.ndarray, joint: str, point: str) -> np.ndarray:
    """(P, 3) rest vector from a canonical joint to a canonical point; the template's where a
    source skeleton puts both at one place (e.g. a neck joint on the chest's end)."""
    b = canonical_rest[:, CANONICAL_POINTS.index(point)] - canonical_rest[:, CANONICAL_POINTS.index(joint)]
    template = _TEMPLATE_POINTS[CANONICAL_POINTS.index(point)] - _TEMPLATE_POINTS[CANONICAL_POINTS.index(joint)]
    return np.where(np.linalg.norm(b, axis=-1, keepdims=True) > 1e-6, b, template)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _posed_rig_point(point: str, A: np.ndarray, joints: np.ndarray, rig_rest: dict[str, np.ndarray], names) -> np.ndarray:
    names = list(names)
    if point in names:
        return joints[:, names.index(point)]
    bone = names.index(RIG_POINTS[point])
    return joints[:, bone] + np.einsum("pij,j->pi", A[:, bone], rig_rest[point] - rig_rest[RIG_POINTS[point]])


def aim_errors(A: np.ndarray, joints: np.ndarray, rig_rest: dict[str, np.ndarray], names,
               world_rotations: np.ndarray, canonical_rest: np.ndarray) -> dict[str, np.ndarray]:
    """Per mapped canonical joint, the angle (degrees, (P,)) between the rig's posed aim direction
    (from its posed joints) and the mocap's (the canonical joint's world rotation applied to its
    rest aim vector): ~0 when the rest alignment and the kinematics are right.

    A (P, J, 3, 3), joints (P, J, 3): the rig's posed world rotations and joints;
    world_rotations (P, 22, 3, 3), canonical_rest (P, 27, 3): as given to :func:`retarget`."""
    names = list(names)
    errors = {}
    for joint, (rig_aim, canon_aim) in AIMS.items():
        a = _posed_rig_point(rig_aim, A, joints, rig_rest, names) - joints[:, names.index(CANONICAL_TO_RIG[joint])]
        b = np.einsum("pij,pj->pi", world_rotations[:, JOINTS.index(joint)], _canonical_aim(canonical_rest, joint, canon_aim))
        errors[joint] = _angle(a, b)
    return errors


REACH = {f"{side}_{name}": (f"{start}.{s}", f"{end}.{s}", f"{side}_{canon_start}", f"{side}_{canon_end}")
         for side, s in (("left", "L"), ("right", "R"))
         for name, start, end, canon_start, canon_end in (("arm", "upperarm01", "finger3-1", "shoulder", "hand"),
                                                          ("leg", "upperleg01", "toe_tip", "hip", "toe"))}
"""Limbs compared by :func:`reach_errors`: name -> (rig start, rig end, canonical start, end)."""


def reach_errors(A: np.ndarray, joints: np.ndarray, rig_rest: dict[str, np.ndarray], names,
                 canonical_posed: np.ndarray) -> dict[str, np.ndarray]:
    """An end-to-end check on whole limbs: the angle (degrees, (P,)) between the shoulder-to-
    knuckles (hip-to-toe-tip) direction of the posed rig and of the mocap's posed canonical
    skeleton. Not zero, since segment proportions differ between the bodies and the rig's toes
    do not bend, but a few degrees when poses transfer right; canonical_posed (P, 27, 3)."""
    errors = {}
    for name, (start, end, canon_start, canon_end) in REACH.items():
        a = _posed_rig_point(end, A, joints, rig_rest, names) - _posed_rig_point(start, A, joints, rig_rest, names)
        b = canonical_posed[:, CANONICAL_POINTS.index(canon_end)] - canonical_posed[:, CANONICAL_POINTS.index(canon_start)]
        errors[name] = _angle(a, b)
    return errors


def hand_and_eye_rotations(rest_joints: np.ndarray, names, finger_curl: np.ndarray, gaze: np.ndarray) -> np.ndarray:
    """Local rotations (P, J, 3, 3) curling the fingers and turning the eyes, identity elsewhere.

    rest_joints (J, 3) of one shape; finger_curl (P, 2, 5) in [0, 1] per hand (left, right) and
    finger (thumb first), scaling :data:`FINGER_MAX_DEGREES`; gaze (P, 2) yaw, pitch in radians
    (both eyes). Flexion turns each finger bone about (bone direction x palm normal), so the tip
    moves to the palm side; the palm normal comes from the rest hand (wrist, index and little
    finger knuckles)."""
    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    count = len(finger_curl)
    out = np.broadcast_to(np.eye(3), (count, len(names), 3, 3)).copy()
    for h, s in enumerate(("L", "R")):
        if f"wrist.{s}" not in index:
            continue
        wrist = rest_joints[index[f"wrist.{s}"]]
        forward = rest_joints[index[f"finger3-1.{s}"]] - wrist
        across = rest_joints[index[f"finger2-1.{s}"]] - rest_joints[index[f"finger5-1.{s}"]]  # little -> index
        normal = np.cross(forward, across) if s == "L" else np.cross(across, forward)
        normal /= np.linalg.norm(normal)
        for finger in range(1, 6):
            for k in range(1, 4):
                bone = index[f"finger{finger}-{k}.{s}"]
                if k < 3:
                    direction = rest_joints[index[f"finger{finger}-{k + 1}.{s}"]] - rest_joints[bone]
                else:
                    direction = rest_joints[bone] - rest_joints[index[f"finger{finger}-{k - 1}.{s}"]]
                axis = np.cross(direction, normal)
                axis /= np.linalg.norm(axis)
                angle = np.radians(FINGER_MAX_DEGREES[finger][k - 1]) * finger_curl[:, h, finger - 1]
                out[:, bone] = _axis_angle(axis, angle)
    eyes = [index[n] for n in ("eye.L", "eye.R") if n in index]
    if eyes:
        turn = _axis_angle(np.array([0.0, 1.0, 0.0]), gaze[:, 0]) @ _axis_angle(np.array([1.0, 0.0, 0.0]), gaze[:, 1])
        for e in eyes:
            out[:, e] = turn
    return out


# -- mocap poses ---------------------------------------------------------------------------------

@dataclass
class MocapPoses:
    """Poses drawn from mocap, on the canonical body, heading removed, pelvis at the origin.

    world_rotations (P, 22, 3, 3); rest (P, 27, 3) and posed (P, 27, 3) canonical points
    (CANONICAL_POINTS); local (P, 22, 4) canonical local rotations; clip (P,) file path relative
    to the mocap root; frame (P,); subject (P,)."""

    world_rotations: np.ndarray
    rest: np.ndarray
    posed: np.ndarray
    local: np.ndarray
    clip: np.ndarray
    frame: np.ndarray
    subject: np.ndarray


def remove_heading(world_rotations: np.ndarray) -> np.ndarray:
    """(P, 3, 3) turns about +Y that bring each pose's root facing (its +Z) onto +Z."""
    forward = world_rotations[:, 0, :, 2]
    yaw = np.arctan2(forward[:, 0], forward[:, 2])
    return _axis_angle(np.array([0.0, 1.0, 0.0]), -yaw)


def sample_mocap_poses(clips, count: int, rng: np.random.Generator, root: Path | None = None,
                       margin: float = 0.1) -> MocapPoses:
    """count frames drawn from clips (humotion.data Clip list): a clip with probability
    proportional to its length, then a frame uniformly in its middle (1 - 2 margin)."""
    if not clips:
        raise ValueError("no mocap clips to draw poses from")
    frames = np.array([c.frames for c in clips], dtype=np.float64)
    choice = rng.choice(len(clips), size=count, p=frames / frames.sum())
    position = rng.uniform(margin, 1.0 - margin, size=count)
    parts = {k: [None] * count for k in ("world", "rest", "posed", "local")}
    frame_of = np.zeros(count, dtype=np.int64)
    for c in np.unique(choice):
        rows = np.flatnonzero(choice == c)
        motion = clips[c].load()
        picks = np.minimum((position[rows] * motion.num_frames).astype(np.int64), motion.num_frames - 1)
        frame_of[rows] = picks
        sub = replace(motion, rotations=motion.rotations[picks], root_positions=motion.root_positions[picks],
                      joint_offsets=None if motion.joint_offsets is None else motion.joint_offsets[picks])
        canon = to_canonical(sub)
        world, positions = (x.double().numpy() for x in canon.world())
        ends = canon.end_site_positions().double().numpy()
        heading = remove_heading(world)
        world = heading[:, None] @ world
        points = np.concatenate([positions, ends], axis=1) - positions[:, :1]
        points = np.einsum("pij,pkj->pki", heading, points)
        local = canon.rotations.double().clone()
        local[:, 0] = rot.matrix_to_quat(torch.as_tensor(world[:, 0]))
        rest = np.concatenate([canon.skeleton.rest_positions(), canon.skeleton.rest_end_site_positions()])
        for i, row in enumerate(rows):
            parts["world"][row], parts["posed"][row] = world[i], points[i]
            parts["local"][row], parts["rest"][row] = local[i].numpy(), rest
    clip_names = [str(clips[c].path.relative_to(root)) if root else str(clips[c].path) for c in choice]
    return MocapPoses(np.stack(parts["world"]), np.stack(parts["rest"]), np.stack(parts["posed"]),
                      np.stack(parts["local"]), np.array(clip_names), frame_of,
                      np.array([clips[c].subject for c in choice]))


def sample_hand_and_gaze(rng: np.random.Generator, count: int, open_fraction: float = 0.3,
                         gaze_fraction: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Random finger curls (count, 2, 5) in [0, 1] (a grip per hand plus per-finger jitter; an
    open hand with probability open_fraction) and gazes (count, 2) (yaw within +-20 degrees,
    pitch within +-12 degrees, with probability gaze_fraction, else straight ahead)."""
    grip = rng.uniform(0.0, 1.0, size=(count, 2, 1)) * (rng.uniform(size=(count, 2, 1)) >= open_fraction)
    curl = np.clip(grip + rng.normal(0.0, 0.15, size=(count, 2, 5)) * (grip > 0), 0.0, 1.0)
    gaze = np.radians(rng.uniform([-20.0, -12.0], [20.0, 12.0], size=(count, 2)))
    gaze *= (rng.uniform(size=(count, 1)) < gaze_fraction)
    return curl, gaze


def sample_expressions(rng: np.random.Generator, count: int, num_actions: int, fraction: float = 0.5,
                       max_active: int = 4) -> np.ndarray:
    """(count, num_actions) sparse facial-action activations: with probability fraction a mesh
    gets 1..max_active actions at strengths uniform in [0.3, 1], else all zeros (neutral)."""
    out = np.zeros((count, num_actions))
    for i in np.flatnonzero(rng.uniform(size=count) < fraction):
        active = rng.choice(num_actions, size=rng.integers(1, max_active + 1), replace=False)
        out[i, active] = rng.uniform(0.3, 1.0, size=len(active))
    return out


# -- splits ------------------------------------------------------------------------------------

@dataclass
class Plan:
    """Which shape and which kind of pose every mesh gets, and its split.

    shape_held_out (N,) bool; mesh_shape (M,) shape index; mesh_pose_held_out (M,) bool;
    mesh_split (M,) index into SPLITS. Mesh m = shape m // K, its k-th pose m % K."""

    shape_held_out: np.ndarray
    mesh_shape: np.ndarray
    mesh_pose_held_out: np.ndarray
    mesh_split: np.ndarray


def plan_splits(num_shapes: int, poses_per_shape: int, rng: np.random.Generator,
                held_out_shapes: float = 0.1, held_out_poses: int | None = None) -> Plan:
    """Hold out round(held_out_shapes * N) shapes (at least one when N >= 2) and, for every shape,
    its last held_out_poses poses (default: K // 8, at least one when K >= 2) drawn from held-out
    mocap subjects. Each mesh's split follows from the two: see SPLITS."""
    n_shapes = round(held_out_shapes * num_shapes)
    if held_out_shapes > 0 and num_shapes >= 2:
        n_shapes = min(max(n_shapes, 1), num_shapes - 1)
    if held_out_poses is None:
        held_out_poses = max(poses_per_shape // 8, 1) if poses_per_shape >= 2 else 0
    if not 0 <= held_out_poses <= poses_per_shape:
        raise ValueError(f"held_out_poses must be in [0, {poses_per_shape}], got {held_out_poses}")
    shape_held = np.zeros(num_shapes, dtype=bool)
    shape_held[rng.choice(num_shapes, size=n_shapes, replace=False)] = True
    mesh_shape = np.repeat(np.arange(num_shapes), poses_per_shape)
    pose_held = np.tile(np.arange(poses_per_shape) >= poses_per_shape - held_out_poses, num_shapes)
    split = shape_held[mesh_shape].astype(np.int64) + 2 * pose_held.astype(np.int64)
    return Plan(shape_held, mesh_shape, pose_held, split)


# -- files ---------------------------------------------------------------------------------------

def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez to path via path.partial and a rename: never a half-written file under the name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as f:
        np.savez(f, **arrays)
    os.replace(partial, path)


def save_json(path: Path, data: dict) -> None:
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(partial, path)


def _load(path: Path) -> dict[str, np.ndarray]:
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: make the data with `python -m humotion.body.dataset --out {path.parent}`")
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def read_manifest(folder: str | Path) -> dict:
    """The run's manifest.json."""
    path = Path(folder) / "manifest.json"
    if not path.exists():
        raise FileNotFoundError(f"no manifest.json in {folder}: not a body data folder (or its run did not finish)")
    return json.loads(path.read_text())


def load_split(folder: str | Path, resolution: str = "full", split: str = "train") -> dict[str, np.ndarray]:
    """Meshes of one split at one resolution: vertices (M, V, 3), mesh_id, shape_id, pose_id,
    rotations (M, J, 4), translation (M, 3), joints (M, J, 3), expression (M, 52), ..."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return _load(Path(folder) / resolution / f"{split}.npz")


def load_model_file(folder: str | Path, resolution: str = "full") -> dict[str, np.ndarray]:
    """Topology and per-shape rest data of one resolution (see the module docstring)."""
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {RESOLUTIONS}, got {resolution!r}")
    return _load(Path(folder) / resolution / "model.npz")


def load_shapes(folder: str | Path) -> dict[str, np.ndarray]:
    return _load(Path(folder) / "shapes.npz")


def load_poses(folder: str | Path) -> dict[str, np.ndarray]:
    return _load(Path(folder) / "poses.npz")


def expression_offsets(model: dict[str, np.ndarray], expression: np.ndarray) -> np.ndarray:
    """Rest-pose expression offsets (M, V, 3) of activations (M, 52): expressive rest mesh minus
    the neutral one."""
    return np.einsum("me,evc->mvc", np.asarray(expression, dtype=np.float32), model["expression_basis"])


def rest_pose_check(model: dict[str, np.ndarray], split: dict[str, np.ndarray], rows=slice(None)) -> np.ndarray:
    """Mean distance (m, per mesh) between each mesh and plain LBS of its rest shape under its pose
    parameters: a consistency check of a data folder (a few mm to cm: the DQS-vs-LBS gap)."""
    rest = model["rest_vertices"][split["shape_id"][rows]] + expression_offsets(model, split["expression"][rows])
    out = []
    for i in range(len(rest)):
        A, t, _ = skinning_transforms(model["rest_joints"][split["shape_id"][rows][i]], model["parents"],
                                      split["rotations"][rows][i:i + 1], split["translation"][rows][i:i + 1])
        lbs = linear_blend_skinning(rest[i], model["skin_weights"], A, t)[0]
        out.append(np.linalg.norm(lbs - split["vertices"][rows][i], axis=-1).mean())
    return np.array(out)


# -- generation ----------------------------------------------------------------------------------

@dataclass
class Settings:
    """One run's settings (they key its resume state)."""

    out: str
    shapes: int = 200
    poses_per_shape: int = 8
    seed: int = 0
    topology: str = "notoes_collapse10pc"
    mocap: str = str(DEFAULT_MOCAP)
    held_out_shapes: float = 0.1
    held_out_poses: int | None = None
    expression_fraction: float = 0.5
    min_age: float = 4.0
    max_age: float = 90.0
    chunk: int = 10

    def key(self) -> str:
        fields = {k: v for k, v in self.__dict__.items() if k not in ("out", "chunk")}
        return hashlib.sha1(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def _rig_points(rest_vertices: np.ndarray, rest_joints: np.ndarray, names) -> dict[str, np.ndarray]:
    """Rest joints by name plus the extra RIG_POINTS found on a full-resolution rest mesh: the top
    of the head and each foot's toe tip (the most forward vertices of its side below the knees)."""
    names = list(names)
    points = {n: rest_joints[i] for i, n in enumerate(names)}
    points["head_top"] = rest_vertices[rest_vertices[:, 1].argmax()]
    knee = min(points["lowerleg01.L"][1], points["lowerleg01.R"][1])
    for s, sign in (("L", 1.0), ("R", -1.0)):
        side = rest_vertices[(rest_vertices[:, 0] * sign > 0) & (rest_vertices[:, 1] < knee)]
        points[f"toe_tip.{s}"] = side[np.argsort(side[:, 2])[-5:]].mean(0)
    return points


class Generator:
    """A data run: the plan (shapes, poses, expressions, splits), then meshes chunk by chunk into
    OUT/.parts (kept on an interrupted run and reused by the next one with the same settings),
    then the final files."""

    def __init__(self, settings: Settings, command: str = "", progress: bool = True):
        from humotion.body import anny_source

        self.settings, self.command, self.progress = settings, command, progress
        self.out = Path(settings.out)
        self.timings: dict[str, float] = {}
        start = time.perf_counter()
        self.bodies = {"full": anny_source.AnnyBody(anny_source.TOPOLOGIES["full"])}
        self.timings["build_full_s"] = time.perf_counter() - start
        if settings.topology and settings.topology != "none":
            start = time.perf_counter()
            self.bodies["low"] = anny_source.AnnyBody(settings.topology)
            self.timings["build_low_s"] = time.perf_counter() - start
        full = self.bodies["full"]
        for name, body in self.bodies.items():
            if body.joint_names != full.joint_names or body.parents != full.parents:
                raise RuntimeError(f"the {name} topology's rig differs from the full one's")
        self.names, self.parents = full.joint_names, full.parents
        self.anny_source = anny_source

    # -- the plan --------------------------------------------------------------------------
    def make_plan(self) -> dict:
        s = self.settings
        rng = np.random.default_rng(s.seed)
        full = self.bodies["full"]
        phenotypes, ages = self.anny_source.sample_phenotypes(full, s.shapes, s.seed, s.min_age, s.max_age)
        plan = plan_splits(s.shapes, s.poses_per_shape, rng, s.held_out_shapes, s.held_out_poses)
        start = time.perf_counter()
        from humotion.data import MotionCollection

        collection = MotionCollection.load(s.mocap, progress=self.progress)
        subjects = collection.split()
        usable = collection.filter(exclude=EXCLUDED_SOURCES)
        pools = {False: usable.filter(subjects=subjects["train"]).clips, True: usable.filter(subjects=subjects["test"]).clips}
        count = len(plan.mesh_shape)
        poses = [None] * count
        for held in (False, True):
            rows = np.flatnonzero(plan.mesh_pose_held_out == held)
            if len(rows):
                drawn = sample_mocap_poses(pools[held], len(rows), rng, root=Path(s.mocap))
                for i, row in enumerate(rows):
                    poses[row] = {k: getattr(drawn, k)[i] for k in drawn.__dataclass_fields__}
        self.timings["mocap_poses_s"] = time.perf_counter() - start
        poses = {k: np.stack([p[k] for p in poses]) for k in poses[0]}
        curl, gaze = sample_hand_and_gaze(rng, count)
        expression = sample_expressions(rng, count, len(full.facial_action_names), s.expression_fraction)
        return dict(plan=plan, phenotypes=phenotypes, ages=ages, poses=poses, curl=curl, gaze=gaze,
                    expression=expression, subjects=subjects)

    # -- one chunk of shapes ---------------------------------------------------------------
    def make_chunk(self, plan: dict, shapes: range) -> dict[str, np.ndarray]:
        full = self.bodies["full"]
        weights = full.skin_weights()
        zones = blend_zones(weights, self.names, self.parents)
        basis = full.expression_basis()
        out: dict[str, list] = {}

        def add(key, value):
            out.setdefault(key, []).append(value)

        for shape in shapes:
            rows = np.flatnonzero(plan["plan"].mesh_shape == shape)
            pheno = plan["phenotypes"][shape:shape + 1]
            rests = {name: body.rest(pheno) for name, body in self.bodies.items()}
            rest_v, rest_j = rests["full"].vertices[0], rests["full"].joints[0]
            for name, rest in rests.items():
                if np.abs(rest.joints[0] - rest_j).max() > 1e-4:
                    raise RuntimeError(f"{name} topology's joints differ from the full one's for shape {shape}")
            points = _rig_points(rest_v, rest_j, self.names)
            poses = plan["poses"]
            extra = hand_and_eye_rotations(rest_j, self.names, plan["curl"][rows], plan["gaze"][rows])
            local = retarget(poses["world_rotations"][rows], poses["rest"][rows], points, self.names, self.parents, extra)
            expression = plan["expression"][rows]
            translation = np.zeros((len(rows), 3))
            translation[:, [0, 2]] = -rest_j[0, [0, 2]]
            vertices = {"full": full.pose(pheno, expression, local, translation)}
            floor = -vertices["full"][..., 1].min(1)
            translation[:, 1] += floor
            vertices["full"][..., 1] += floor[:, None]
            for name, body in self.bodies.items():
                if name != "full":
                    vertices[name] = body.pose(pheno, expression, local, translation)
            A, t, joints = skinning_transforms(rest_j, self.parents, local, translation)
            lbs = linear_blend_skinning(rest_v + np.einsum("ke,evc->kvc", expression, basis), weights, A, t)
            gap = np.linalg.norm(lbs - vertices["full"], axis=-1)
            for region, zone in zones.items():
                add(f"gap_{region}", gap[:, zone].mean(1))
            add("gap_all", gap.mean(1))
            for joint, error in aim_errors(A, joints, points, self.names, poses["world_rotations"][rows],
                                           poses["rest"][rows]).items():
                add(f"aim_{joint}", error)
            for point, error in reach_errors(A, joints, points, self.names, poses["posed"][rows]).items():
                add(f"reach_{point}", error)
            add("rows", rows)
            add("rotations", rot.matrix_to_quat(torch.as_tensor(local)).numpy().astype(np.float32))
            add("translation", translation.astype(np.float32))
            add("joints", joints.astype(np.float32))
            for name, v in vertices.items():
                add(f"vertices_{name}", v.astype(np.float32))
            for name, rest in rests.items():
                add(f"rest_vertices_{name}", rest.vertices.astype(np.float32))
            add("rest_joints", rest_j[None].astype(np.float32))
        return {k: np.concatenate(v) for k, v in out.items()}

    # -- the whole run ---------------------------------------------------------------------
    def run(self) -> dict:
        s = self.settings
        self.out.mkdir(parents=True, exist_ok=True)
        parts = self.out / ".parts"
        state = parts / "settings.json"
        if parts.exists() and (not state.exists() or json.loads(state.read_text()).get("key") != s.key()):
            log.info("discarding the parts of a run with other settings in %s", parts)
            shutil.rmtree(parts)
        parts.mkdir(exist_ok=True)
        save_json(state, {"key": s.key(), "settings": s.__dict__})

        start = time.perf_counter()
        plan = self.make_plan()
        self.timings["plan_s"] = time.perf_counter() - start
        chunks = [range(a, min(a + s.chunk, s.shapes)) for a in range(0, s.shapes, s.chunk)]
        start, made = time.perf_counter(), 0
        bar = tqdm(total=len(plan["plan"].mesh_shape), desc="body meshes", unit="mesh", disable=not self.progress)
        results = []
        for i, shapes in enumerate(chunks):
            path = parts / f"chunk-{i:04d}.npz"
            if path.exists():
                results.append(_load(path))
            else:
                result = self.make_chunk(plan, shapes)
                save_npz(path, result)
                results.append(result)
                made += len(result["rows"])
            bar.update(len(results[-1]["rows"]))
        bar.close()
        elapsed = time.perf_counter() - start
        self.timings["meshes_s"] = elapsed
        self.timings["per_mesh_s"] = elapsed / made if made else float("nan")
        chunk = {k: np.concatenate([r[k] for r in results]) for k in results[0]}
        manifest = self.write(plan, chunk)
        shutil.rmtree(parts)
        return manifest

    def write(self, plan: dict, chunk: dict[str, np.ndarray]) -> dict:
        s, full = self.settings, self.bodies["full"]
        p = plan["plan"]
        if not np.array_equal(chunk["rows"], np.arange(len(p.mesh_shape))):
            raise RuntimeError("chunks do not cover the meshes in order: delete OUT/.parts and run again")
        rest_full = chunk["rest_vertices_full"]
        measures = full.anthropometry(rest_full.astype(np.float64))
        save_npz(self.out / "shapes.npz", dict(
            shape_id=np.arange(s.shapes), phenotypes=plan["phenotypes"].astype(np.float32),
            phenotype_names=np.array(full.phenotype_names), age_years=plan["ages"].astype(np.float32),
            held_out=p.shape_held_out, **{k: v.astype(np.float32) for k, v in measures.items()}))
        poses = plan["poses"]
        save_npz(self.out / "poses.npz", dict(
            pose_id=np.arange(len(p.mesh_shape)), clip=poses["clip"], frame=poses["frame"], subject=poses["subject"],
            held_out=p.mesh_pose_held_out, canonical_rotations=poses["local"].astype(np.float32),
            canonical_joint_names=np.array(JOINTS), finger_curl=plan["curl"].astype(np.float32),
            gaze=plan["gaze"].astype(np.float32)))

        labels, label_names = full.part_labels()
        template_full = full.template_vertices()
        sizes = {}
        for name, body in self.bodies.items():
            part = labels if name == "full" else self.anny_source.transfer_labels(template_full, labels, body.template_vertices())
            regions = {f"region_{r}": np.isin(part, [label_names.index(x) for x in parts])
                       for r, parts in self.anny_source.REGION_PARTS.items()}
            folder = self.out / name
            save_npz(folder / "model.npz", dict(
                faces=body.faces, joint_names=np.array(self.names), parents=np.array(self.parents),
                rest_vertices=chunk[f"rest_vertices_{name}"], rest_joints=chunk["rest_joints"],
                skin_weights=body.skin_weights(), expression_basis=body.expression_basis(),
                facial_action_names=np.array(body.facial_action_names), part=part, part_names=np.array(label_names),
                **regions))
            for k, split in enumerate(SPLITS):
                rows = np.flatnonzero(p.mesh_split == k)
                arrays = dict(vertices=chunk[f"vertices_{name}"][rows], mesh_id=rows, shape_id=p.mesh_shape[rows],
                              pose_id=rows, rotations=chunk["rotations"][rows], translation=chunk["translation"][rows],
                              joints=chunk["joints"][rows], expression=plan["expression"][rows].astype(np.float32))
                if name == "full":
                    arrays["lbs_gap_mm"] = (chunk["gap_all"][rows] * 1000).astype(np.float32)
                save_npz(folder / f"{split}.npz", arrays)
            sizes[name] = dict(vertices=body.num_vertices, faces=len(body.faces))

        counts = {split: int((p.mesh_split == k).sum()) for k, split in enumerate(SPLITS)}
        gap = {region[4:]: round(float(chunk[region].mean() * 1000), 3) for region in chunk if region.startswith("gap_")}
        gap_max = round(float(chunk["gap_all"].max() * 1000), 3)
        aims = {k[4:]: round(float(np.percentile(v, 99)), 4) for k, v in chunk.items() if k.startswith("aim_")}
        reach = {k[6:]: [round(float(np.percentile(v, q)), 2) for q in (50, 90, 99)] for k, v in chunk.items()
                 if k.startswith("reach_")}
        manifest = dict(
            format_version=FORMAT_VERSION, command=self.command, seed=s.seed, settings=s.__dict__,
            anny_version=self.anny_source.anny_version(), rig=self.anny_source.DEFAULT_RIG,
            topologies={name: body.topology for name, body in self.bodies.items()}, resolutions=sizes,
            joints=len(self.names), shapes=s.shapes, held_out_shapes=int(p.shape_held_out.sum()),
            poses_per_shape=s.poses_per_shape, meshes=len(p.mesh_shape), splits=counts,
            mocap_subjects={"train": plan["subjects"]["train"], "held_out": plan["subjects"]["test"]},
            excluded_sources=list(EXCLUDED_SOURCES),
            expressive_meshes=int((plan["expression"] > 0).any(1).sum()),
            lbs_vs_dqs_mean_mm=gap, lbs_vs_dqs_worst_mesh_mm=gap_max,
            retarget_aim_error_deg_p99=aims, retarget_limb_error_deg_p50_p90_p99=reach,
            timings_s={k: round(v, 3) for k, v in self.timings.items()},
            bytes=None, licence=LICENCE,
            conventions="metres, Y up, characters face +Z, quaternions wxyz; see humotion/body/dataset.py")
        manifest["bytes"] = sum(f.stat().st_size for f in self.out.rglob("*.npz") if ".parts" not in f.parts)
        save_json(self.out / "manifest.json", manifest)
        return manifest


def generate(settings: Settings, command: str = "", progress: bool = True) -> dict:
    """Make a data folder (see the module docstring); returns the manifest."""
    return Generator(settings, command, progress).run()


# -- command line --------------------------------------------------------------------------------

@click.command("body-data", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
               epilog="\b\nExamples:\n  python -m humotion.body.dataset --out runs/body_data\n"
                      "  python -m humotion.body.dataset --out /tmp/tiny --shapes 4 --poses-per-shape 2")
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder (resumes a run there).")
@click.option("--shapes", default=200, show_default=True, help="Body shapes (phenotypes) to draw.")
@click.option("--poses-per-shape", default=8, show_default=True, help="Posed meshes per shape.")
@click.option("--seed", default=0, show_default=True)
@click.option("--topology", default="notoes_collapse10pc", show_default=True,
              type=click.Choice(["notoes_collapse10pc", "notoes_collapse5pc", "notoes_collapse3pc", "none"]),
              help="Anny topology of the low resolution (1,229 / 615 / 369 vertices), or none.")
@click.option("--mocap", default=str(DEFAULT_MOCAP), show_default=True, type=click.Path(exists=True, file_okay=False),
              help="Mocap folder tree the poses come from.")
@click.option("--held-out-shapes", default=0.1, show_default=True, help="Fraction of shapes held out.")
@click.option("--held-out-poses", type=int, help="Poses per shape from held-out subjects (default K // 8, >= 1).")
@click.option("--expression-fraction", default=0.5, show_default=True, help="Share of meshes with a facial expression.")
@click.option("--min-age", default=4.0, show_default=True, help="Youngest morphological age (years).")
@click.option("--max-age", default=90.0, show_default=True, help="Oldest morphological age (years).")
@click.option("--chunk", default=10, show_default=True, help="Shapes per resumable chunk.")
@click.option("--threads", default=1, show_default=True, help="torch CPU threads.")
@click.option("--anny-cache", type=click.Path(file_okay=False), help="Anny's model cache (default $ANNY_CACHE_DIR or ~/.cache/anny).")
def main(out, shapes, poses_per_shape, seed, topology, mocap, held_out_shapes, held_out_poses, expression_fraction,
         min_age, max_age, chunk, threads, anny_cache):
    """Generate registered body meshes (Anny shapes x CMU poses x facial expressions, DQS-skinned,
    two resolutions sharing one skeleton) with held-out shapes and poses."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(threads)
    if anny_cache:
        os.environ["ANNY_CACHE_DIR"] = anny_cache
    settings = Settings(out=out, shapes=shapes, poses_per_shape=poses_per_shape, seed=seed, topology=topology,
                        mocap=mocap, held_out_shapes=held_out_shapes, held_out_poses=held_out_poses,
                        expression_fraction=expression_fraction, min_age=min_age, max_age=max_age, chunk=chunk)
    command = "python -m humotion.body.dataset " + " ".join(sys.argv[1:])
    manifest = generate(settings, command=command)
    click.echo(f"wrote {manifest['meshes']} meshes ({manifest['splits']}) to {out}: "
               f"{manifest['bytes'] / 1e6:.1f} MB; LBS vs DQS mean gap {manifest['lbs_vs_dqs_mean_mm']['all']:.2f} mm")


if __name__ == "__main__":
    main()
