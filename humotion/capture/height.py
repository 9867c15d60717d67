"""Standing heights relative to a reference person of known height on the same floor.

One camera cannot tell a tall person far away from a short one nearby: scaling a person's
reconstruction about the camera centre leaves its image unchanged, and video capture places a
person of wrongly assumed height H' at a depth wrong by the factor H' / H. Two people walking on
one flat floor break the tie. Person A's height is given, so A's feet sit on the real floor; a
person B reconstructed at an assumed height H'_B has feet on the floor scaled by H'_B / H_B
about the camera centre: a plane of the same orientation at another distance from the camera.
With the floor written n . x = d (camera frame, metres; n the unit "down" direction, d the
camera's height above the floor), each person i's foot contacts lie on n . x = d_i, and B's
height is H'_B * d_A / d_B.

Estimation (:func:`fit_floor`): per frame, each person's lowest sole point along n (the heel and
big-toe keypoints of the fitted body, each moved down by its height above the sole in the
template's rest pose); one floor shared by everyone, seen at a distance d_i by each person's
reconstruction, by iteratively reweighted linear least squares in relative depth (Cauchy
weights: a swinging or flying foot is not on the floor), with a weak prior pulling n towards
the "down" of the lifted bodies (ankles minus neck, averaged over frames), which is all there
is to go on when nobody moves. The floor's orientation is only as good as the spread of
everyone's contacts: a person walking about pins it down; people standing still leave it to
the bodies' down direction, which is off by several degrees (2-10 measured). A tilt error
moves the floor under B by (tilt) x (distance between the people) / (camera height), so
:func:`fit_floor` propagates its uncertainty into a standard error of each scale factor, and
:func:`estimate_heights` keeps the assumed height (with a warning) where that error is too large
(people standing still far apart, a camera near the floor), where a person was barely seen on
the floor, or where the result is no plausible height. Measured (bench/height_from_reference.py)
the estimate is good to about 10% (a floor tilted by a few degrees), far better than a default
for children, little better for adults.

Assumes a static camera (the floor fixed in its frame) and a flat floor both people stand on;
the camera's intrinsics are the pipeline's (a wrong focal length biases the result).
Measured on synthetic two-person scenes of held-out mocap: bench/height_from_reference.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import body_keypoints_3d
from humotion.motion import Motion
from humotion.skeleton import Skeleton, forward_kinematics

SOLE_KEYPOINTS = ("left_heel", "right_heel", "left_big_toe", "right_big_toe")
MIN_CONFIDENCE = 0.3     # detector confidence below which a sole keypoint is not used
_SOLE = [KEYPOINTS.index(k) for k in SOLE_KEYPOINTS]
_NECK, _ANKLES = JOINTS.index("neck"), [JOINTS.index("left_ankle"), JOINTS.index("right_ankle")]


@dataclass
class FloorContacts:
    """Where one person's soles were, in the camera frame (x right, y down, z forward).

    points: (T, 4, 3) metres, the SOLE_KEYPOINTS of the fitted body per frame (at the person's
        assumed height); lift: (4,) metres, their height above the sole in the template's rest
        pose; weight: (T, 4) in [0, 1], the detector's confidence in them (0: not seen);
    down: (T, 3) unit vectors, the body's ankles-minus-neck direction per frame."""

    points: torch.Tensor
    lift: torch.Tensor
    weight: torch.Tensor
    down: torch.Tensor

    @staticmethod
    def concat(parts: list["FloorContacts"]) -> "FloorContacts":
        """One person's contacts over several segments, frames one after the other."""
        return FloorContacts(torch.cat([p.points for p in parts]), parts[0].lift,
                             torch.cat([p.weight for p in parts]), torch.cat([p.down for p in parts]))


def sole_lift(skeleton: Skeleton) -> torch.Tensor:
    """(4,) metres: height of the SOLE_KEYPOINTS above the lowest point of the rest pose."""
    rest, ends = skeleton.rest_positions(), skeleton.rest_end_site_positions()
    eye = torch.eye(3).expand(len(JOINTS), 3, 3)
    points = body_keypoints_3d(eye, rest, skeleton)
    floor = torch.cat([rest, ends])[:, 1].min()
    return points[_SOLE, 1] - floor


def contacts_of(rotvecs: torch.Tensor, root: torch.Tensor, skeleton: Skeleton,
                confidence: torch.Tensor) -> FloorContacts:
    """FloorContacts of a fitted segment: rotvecs (T, 22, 3) joint rotations (joint 0 global,
    camera frame), root (T, 3) metres in the camera frame, on skeleton (the person's template);
    confidence (T, 21) the detector's per keypoint (KEYPOINTS order)."""
    world_r, joints = forward_kinematics(rot.convert(rotvecs, "rotvec", "matrix"), root, skeleton.offsets,
                                         skeleton.parents)
    points = body_keypoints_3d(world_r, joints, skeleton)[:, _SOLE]
    down = torch.nn.functional.normalize(joints[:, _ANKLES].mean(1) - joints[:, _NECK], dim=-1)
    weight = torch.nan_to_num(torch.as_tensor(confidence, dtype=torch.float32)[:, _SOLE]).clamp(0, 1)
    return FloorContacts(points.float(), sole_lift(skeleton), weight, down.float())


@dataclass
class FloorFit:
    """The floor n . x = d in the camera frame, seen from each person.

    normal: (3,) unit "down" vector (camera frame); offsets: {person: d_i metres}, the floor's
    distance from the camera as person i's reconstruction has it; contacts: {person: frames with
    a foot on the floor, weighted by confidence and robust weight}; covariance: (2 + P, 2 + P)
    of the unknowns of fit_floor, m (3, per metre) and the ratios d_i / d_ref of the P - 1
    people after the reference; order: the people, the reference first."""

    normal: torch.Tensor
    offsets: dict[int, float]
    contacts: dict[int, float]
    covariance: np.ndarray = field(repr=False)
    order: list[int] = field(default_factory=list)

    def scale(self, person: int) -> tuple[float, float]:
        """(s, standard error of log s): person's reconstruction times s puts them on the
        reference's floor (their height is s times the one assumed)."""
        k = self.order.index(person)
        if k == 0:
            return 1.0, 0.0
        ratio = self.offsets[person] / self.offsets[self.order[0]]
        return 1.0 / ratio, math.sqrt(max(float(self.covariance[2 + k, 2 + k]), 0.0)) / ratio


def fit_floor(contacts: dict[int, FloorContacts], reference: int, prior_std_deg: float = 6.0,
              frames_per_sample: float = 60.0, min_confidence: float = MIN_CONFIDENCE,
              iterations: int = 10) -> FloorFit:
    """The shared floor normal and each person's offset from everyone's contacts.

    Unknowns: m = n / d_ref (the floor as the reference person's reconstruction has it) and, per
    other person i, k_i = d_i / d_ref. Each frame's lowest sole point q of person i (camera
    frame, metres) is on the floor when m . q = k_i (k_ref = 1): linear least squares. The
    reconstruction's errors are mostly along the ray from the camera and in proportion to the
    distance (the depth comes from a body's 2D size), which makes m . q - k_i proportional to
    k_i times the relative depth error: residuals are weighted by 1 / k_i, and the ray
    directions, which the image fixes, carry the geometry. (A plane fitted by perpendicular
    distances tilts to follow the depth errors along the rays.) Cauchy weights drop feet off the
    floor; a prior keeps n within prior_std_deg (degrees) of the bodies' mean down direction,
    all there is to go on when nobody moves. frames_per_sample: consecutive frames count as one
    independent observation (their errors are correlated); min_confidence: soles seen less
    surely are not used. ValueError when the reference has no sole seen on 3 frames, or when the
    contacts put the floor more than 45 degrees off the bodies' down direction (no floor: a
    moving camera, stairs).
    """
    data = {}
    for person, c in contacts.items():
        frames = (c.weight >= min_confidence).any(1)
        if int(frames.sum()) >= 3:
            data[person] = (c.points[frames].double(), c.lift.double(), c.weight[frames].double())
    if reference not in data:
        raise ValueError(f"person {reference}'s feet were not seen on the floor (on 3 frames or more)")
    people = [reference] + [p for p in data if p != reference]
    downs = torch.cat([contacts[p].down for p in people]).double()
    prior = torch.nn.functional.normalize(downs.mean(0), dim=0)
    normal, ratios = prior.clone(), torch.ones(len(people), dtype=torch.float64)
    unknowns = 3 + len(people) - 1
    off_prior = torch.eye(3, dtype=torch.float64) - torch.outer(prior, prior)
    solution = None
    for _ in range(iterations):
        rows, targets, weights, owner = [], [], [], []
        for k, person in enumerate(people):
            points, lift, weight = data[person]
            soles = points + lift[:, None] * normal                              # (T, 4, 3) on the sole
            lowest = torch.where(weight >= min_confidence, soles @ normal, -torch.inf).argmax(1)
            t = torch.arange(len(lowest))
            q, w = soles[t, lowest], weight[t, lowest]
            row = torch.zeros(len(q), unknowns, dtype=torch.float64)
            row[:, :3] = q
            if k:
                row[:, 2 + k] = -1.0
            rows.append(row / ratios[k])
            targets.append(torch.full((len(q),), 1.0 if k == 0 else 0.0, dtype=torch.float64))
            weights.append(w)
            owner.append(torch.full((len(q),), k))
        a, b, w, owner_all = torch.cat(rows), torch.cat(targets), torch.cat(weights), torch.cat(owner)
        if solution is None:                 # first round: the prior's normal, everyone's soles weighted alike
            robust, sigma = w, 0.05
            offset = float((rows[0][:, :3] @ normal).median())
        else:
            r = a @ solution - b             # relative depth errors
            sigma = max(0.01, float(1.4826 * (r - r.median()).abs().median()))
            robust = w / (1 + (r / (2 * sigma)) ** 2)
        information = (a.T * robust) @ a / (sigma**2 * frames_per_sample)
        rhs = (a.T * robust) @ b / (sigma**2 * frames_per_sample)
        information[:3, :3] += off_prior * offset**2 / math.radians(prior_std_deg) ** 2
        solution = torch.linalg.solve(information, rhs)
        m = solution[:3]
        offset = float(1.0 / m.norm())
        normal = m / m.norm()
        if float(normal @ prior) < math.cos(math.radians(45)):
            raise ValueError("the feet do not describe a floor below the people (the camera moving, or no flat floor?)")
        ratios = torch.cat([torch.ones(1, dtype=torch.float64), solution[3:]]).clamp_min(1e-3)
    covariance = torch.linalg.inv(information).numpy()
    counts = {p: float(robust[owner_all == k].sum()) for k, p in enumerate(people)}
    return FloorFit(normal.float(), {p: offset * float(ratios[k]) for k, p in enumerate(people)}, counts,
                    covariance.astype(np.float64), people)


def estimate_heights(contacts: dict[int, FloorContacts], assumed: dict[int, float], reference: int,
                     people: list[int] | None = None, max_log_std: float = 0.2,
                     min_contacts: float = 15.0) -> tuple[dict[int, float], list[str]]:
    """Standing heights (metres) relative to the reference person's.

    contacts: {person: FloorContacts} of their fits at the assumed heights {person: metres} (the
    reference's being their true height). people: whose heights to estimate (default: everyone
    but the reference; everyone's contacts help find the floor). Returns ({person: height} for
    those whose height could be estimated, warnings for those that could not: they keep the
    assumed height). max_log_std: largest standard error of the log scale factor accepted (0.2:
    about 20%); min_contacts: fewest frames with a foot on the floor (FloorFit.contacts).
    ValueError when the reference is not among the people or was never seen with a foot on the
    floor."""
    if reference not in contacts:
        raise ValueError(f"the height reference, person {reference}, was not found in the video "
                         f"(people: {', '.join(map(str, sorted(contacts))) or 'none'})")
    never = (f"the height reference, person {reference}, was never seen with a foot on the floor; "
             "give the others' heights with --height instead")
    if int((contacts[reference].weight >= MIN_CONFIDENCE).any(1).sum()) < 3:
        raise ValueError(never)
    others = [p for p in sorted(contacts) if p != reference] if people is None else sorted(set(people) - {reference})
    try:
        fit = fit_floor(contacts, reference)
    except ValueError as error:
        return {}, [f"height of person {p} not estimated: {error}; they keep {assumed[p]:.2f} m" for p in others]
    if fit.contacts.get(reference, 0.0) < min_contacts:
        raise ValueError(never)
    heights, warnings = {}, []
    for person in others:
        keep = f"person {person} keeps {assumed[person]:.2f} m"
        if fit.contacts.get(person, 0.0) < min_contacts:
            warnings.append(f"height of person {person} not estimated: their feet were barely seen on the floor; "
                            f"{keep}")
            continue
        s, log_std = fit.scale(person)
        height = assumed[person] * s
        if log_std > max_log_std:
            warnings.append(f"height of person {person} not estimated: the floor is not pinned down well enough "
                            f"(+-{100 * log_std:.0f}%; people standing still or far apart); {keep}")
        elif not 0.5 <= height <= 2.5:
            warnings.append(f"height of person {person} not estimated: {height:.2f} m is implausible; {keep}")
        else:
            heights[person] = height
    return heights, warnings


def placed_on_floor(motion: Motion, height: float, yaw: float, centre) -> Motion:
    """The motion scaled to a standing height (m), turned by yaw (radians) about the vertical, its
    mean horizontal root position at centre (x, z) metres and the median per-frame lowest sole at
    y = 0: one person of a synthetic scene (bench/height_from_reference.py and the tests)."""
    factor = height / motion.skeleton.height()
    skeleton = motion.skeleton.scaled(factor)
    turn = rot.convert(torch.tensor([0.0, yaw, 0.0]), "rotvec", "matrix")
    rotations = motion.rotations.clone()
    rotations[:, 0] = rot.matrix_to_quat(turn @ rot.quat_to_matrix(rotations[:, 0]))
    root = motion.root_positions * factor @ turn.T
    root[:, [0, 2]] += torch.as_tensor(centre, dtype=root.dtype) - root[:, [0, 2]].mean(0)
    moved = Motion(skeleton, rotations, root, motion.fps, name=motion.name)
    world_r, world_p = moved.world()
    soles = body_keypoints_3d(world_r, world_p, skeleton)[:, _SOLE, 1] - sole_lift(skeleton)
    root[:, 1] -= soles.amin(1).median()
    return Motion(skeleton, rotations, root, motion.fps, name=motion.name)
