"""One static camera, one floor, one world: the camera's pitch, roll and height from the people.

    pose = estimate_camera(fits)                  # fits: people in the camera frame (metres)
    world = pose.to_world(points_in_camera)       # Y up, floor at y = 0, camera at (0, height, 0)

The camera is assumed static: one pose for the whole video (a moving camera is reported by
:func:`floor_drift` and by the background motion measured while frames are read, not modelled).

How the pose is found (camera frame: OpenCV's, x right, y down, z forward):

0. From the image alone, when people are seen upright on enough frames and places
   (humotion.capture.metrology: single-view metrology with people as vertical references of
   known height): their feet and bodies fix the horizon and the camera's height without the
   lifter, whose bodies can lean or crouch. Otherwise, from the lifted people:
1. People's vertical axes: on frames where a person stands (both knees straight, the trunk in
   line with the legs) the line from the ankles' midpoint to the neck is vertical, on average
   (quiet standing keeps the body's mass over the feet; walking leans a few degrees). The
   median of these axes over everyone is a first "up" (u0), when there are enough of them
   (MIN_STANDING frames, or a fifth of all frames).
2. The floor: the soles (heels and big toes) of feet in contact (the lower foot, slow) of all
   people on all frames, fitted with a plane by RANSAC (inliers within 5 cm, a normal within 35
   degrees of u0), refined by least squares on the inliers. The plane is used when its inliers
   spread over the floor (0.15 m standard deviation across the second direction: people at
   different places, not one person standing still); then up is its normal and the camera's
   height its distance to the camera. When they spread along one line only (a walk to and fro),
   up is u0 made square to that line ("people and floor line"). Otherwise up is u0 ("people").
   Without the plane the camera's height is the median over frames of the lowest point's distance
   along up.
3. Given values win: a known pitch (and roll 0) replaces the estimated up; a known camera height
   replaces the estimated one.

The world frame (:meth:`CameraPose.world_from_camera`): Y is up; the camera is at (0, height, 0)
and looks along -Z, tilted by its pitch and roll; X is to the camera's right. A person facing
the camera faces +Z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import VirtualCamera

SOLES = [KEYPOINTS.index(k) for k in ("left_heel", "left_big_toe", "right_heel", "right_big_toe")]
"""Keypoints on the soles (body_keypoints_3d layout): left heel, left toe, right heel, right toe."""
SOLE_ANKLES = [KEYPOINTS.index(k) for k in ("left_ankle", "left_ankle", "right_ankle", "right_ankle")]
"""The ankle above each of SOLES."""
_J = {name: i for i, name in enumerate(JOINTS)}
LEVEL_UP = (0.0, -1.0, 0.0)
"""Up in the camera frame of a level camera (no pitch, no roll)."""
MIN_STANDING = 10
"""Standing frames needed before people's axes are trusted (or a fifth of all frames, when fewer:
one for a photo). The lifter's few upright-looking frames of people who crouch, climb or play
ball most of the time are no guide (on the CMU test clips: 0-11 of 300)."""


@dataclass
class CameraPose:
    """A static camera over a flat floor. up: (3,) the world's up direction in the camera frame
    (unit); height: the camera centre's height above the floor, metres; source: how up was found
    ("given", "floor", "people and floor line", "people" or "level"); contacts: sole points the floor was fitted on;
    spread: metres, their spread across the floor (second standard deviation)."""

    up: torch.Tensor
    height: float
    source: str
    contacts: int = 0
    spread: float = 0.0

    @property
    def pitch_deg(self) -> float:
        """Degrees the optical axis points below the horizon (negative: up)."""
        return math.degrees(math.asin(float(-self.up[2].clamp(-1, 1))))

    @property
    def roll_deg(self) -> float:
        """Degrees the image is turned clockwise about the optical axis (the horizon tilted)."""
        return math.degrees(math.atan2(float(self.up[0]), float(-self.up[1])))

    def world_from_camera(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(rotation (3, 3), translation (3,)): world = rotation @ camera point + translation."""
        up = torch.nn.functional.normalize(self.up.float(), dim=0)
        forward = torch.tensor([0.0, 0.0, 1.0]) - up[2] * up               # optical axis, horizontal part
        forward = torch.nn.functional.normalize(forward, dim=0)
        z_axis = -forward
        x_axis = torch.linalg.cross(up, z_axis)
        return torch.stack([x_axis, up, z_axis]), torch.tensor([0.0, self.height, 0.0])

    def to_world(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) camera-frame points (metres) in the world frame."""
        rotation, translation = self.world_from_camera()
        return points @ rotation.T.to(points.dtype) + translation.to(points.dtype)

    def floor_height(self, points: torch.Tensor) -> torch.Tensor:
        """(...) heights above the floor (metres) of (..., 3) camera-frame points."""
        return points @ self.up.to(points.dtype) + self.height

    def camera_in_world(self, camera: VirtualCamera) -> VirtualCamera:
        """camera's intrinsics with this pose as extrinsics (world to camera)."""
        rotation, translation = self.world_from_camera()
        return VirtualCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                             rotation.T, -(rotation.T @ translation))

    def describe(self) -> dict:
        """The pose as plain numbers for capture.json."""
        rotation, translation = self.world_from_camera()
        return {"pitch_deg": round(self.pitch_deg, 2), "roll_deg": round(self.roll_deg, 2),
                "height_m": round(self.height, 4), "found_from": self.source,
                "up_in_camera": [round(float(v), 5) for v in self.up],
                "rotation_world_to_camera": [[round(float(v), 6) for v in row] for row in rotation.T],
                "position_m": [round(float(v), 4) for v in translation]}


def up_from_pitch(pitch_deg: float, roll_deg: float = 0.0) -> torch.Tensor:
    """(3,) the world's up in the frame of a camera pitched down by pitch_deg and rolled by roll_deg."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    up = torch.tensor([0.0, -math.cos(p), -math.sin(p)])
    # roll turns the image clockwise: the up direction turns the other way about the optical axis
    c, s = math.cos(r), math.sin(r)
    return torch.tensor([c * up[0] - s * up[1], s * up[0] + c * up[1], up[2]]) if roll_deg else up


def standing_axes(joints: torch.Tensor, max_bend_deg: float = 25.0, min_knee_deg: float = 150.0) -> torch.Tensor:
    """(N, 3) unit ankles-to-neck axes of the frames of joints (T, 22, 3) where the person stands:
    both knees straighter than min_knee_deg and the trunk within max_bend_deg of the legs."""
    def unit(v):
        return torch.nn.functional.normalize(v, dim=-1)

    knees_ok = torch.ones(len(joints), dtype=torch.bool)
    for side in ("left", "right"):
        hip, knee, ankle = (joints[:, _J[f"{side}_{n}"]] for n in ("hip", "knee", "ankle"))
        cos = (unit(hip - knee) * unit(ankle - knee)).sum(-1)
        knees_ok &= cos < math.cos(math.radians(min_knee_deg))
    ankles = (joints[:, _J["left_ankle"]] + joints[:, _J["right_ankle"]]) / 2
    legs, trunk = unit(joints[:, _J["pelvis"]] - ankles), unit(joints[:, _J["neck"]] - joints[:, _J["pelvis"]])
    straight = (legs * trunk).sum(-1) > math.cos(math.radians(max_bend_deg))
    return unit(joints[:, _J["neck"]] - ankles)[knees_ok & straight]


def median_direction(directions: torch.Tensor) -> torch.Tensor | None:
    """The unit vector along the component-wise median of (N, 3) unit vectors (None when N = 0)."""
    if len(directions) == 0:
        return None
    return torch.nn.functional.normalize(directions.median(0).values, dim=0)


def contact_soles(soles: torch.Tensor, up: torch.Tensor, fps: float, near: float = 0.04,
                  max_speed: float = 0.8) -> torch.Tensor:
    """(T, 4) bool: sole points (T, 4, 3) (camera frame, SOLES order) that touch the floor as far
    as one person's motion tells: within `near` metres (along up) of the frame's lowest sole point
    and moving slower than max_speed m/s. A single frame counts as still."""
    height = soles @ up
    low = height - height.amin(1, keepdim=True) < near
    if len(soles) < 2:
        return low
    speed = torch.zeros(soles.shape[:2])
    step = (soles.diff(dim=0).norm(dim=-1) * fps)
    speed[1:] += step / 2
    speed[:-1] += step / 2
    speed[0] *= 2
    speed[-1] *= 2
    return low & (speed < max_speed)


STILL_WINDOW = 0.15
"""Seconds either side of a frame over which a sole's 2D keypoint must stay still (still_soles)."""
STILL_NEAR = 0.2
"""Metres along up: how far above the frame's lowest sole a still sole may be and count as planted."""


def still_soles(keypoints: torch.Tensor, confidence: torch.Tensor, times: torch.Tensor, soles: torch.Tensor,
                up: torch.Tensor, focal: float, max_speed: float) -> torch.Tensor:
    """(T, 4) bool: soles planted as the image tells, for a static camera. A planted sole's 2D
    keypoint stays put, whatever the lifter makes of its depth; so a sole counts as planted when
    its detected pixel moves slower than max_speed m/s at the sole's depth between STILL_WINDOW
    seconds before and after the frame, and the fit's sole is within STILL_NEAR of the frame's
    lowest along up. A sole the detector does not give (MoveNet has no heels or toes) is judged
    by its ankle. A motion along the line of sight, which leaves the pixels still, is not told
    apart.

    keypoints (T, 21, 2) pixels and confidence (T, 21): the detections (KEYPOINTS layout; a point
    is seen at confidence >= 0.3 at both ends of the window). times (T,) seconds. soles (T, 4, 3):
    the fit's soles (SOLES order), camera frame, metres. up (3,): the floor's normal. focal: pixels."""
    times = torch.as_tensor(times, dtype=torch.float64)
    before = torch.searchsorted(times, times - STILL_WINDOW).clamp(max=len(times) - 1)
    after = (torch.searchsorted(times, times + STILL_WINDOW, right=True) - 1).clamp(min=0)
    span = (times[after] - times[before]).float()[:, None]
    seen = (confidence[before] >= 0.3) & (confidence[after] >= 0.3) & (span > 0)            # (T, 21)
    moved = (keypoints[after] - keypoints[before]).norm(dim=-1)                               # (T, 21) pixels
    sole_seen = seen[:, SOLES]
    moved = torch.where(sole_seen, moved[:, SOLES], moved[:, SOLE_ANKLES])
    usable = sole_seen | seen[:, SOLE_ANKLES]
    speed = moved * soles[..., 2].clamp_min(0.1) / focal / span.clamp_min(1e-3)
    height = soles @ up
    return usable & (speed < max_speed) & (height - height.amin(1, keepdim=True) < STILL_NEAR)


def fit_floor(points: np.ndarray, up0: np.ndarray, threshold: float = 0.05, iterations: int = 300,
              max_tilt_deg: float = 35.0, seed: int = 0) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC plane through (N, 3) points: (normal (3,) oriented along up0, offset d with
    normal . x + d = 0 on the plane, inlier mask (N,)), refined by least squares on the inliers;
    None when fewer than 3 points or no plane within max_tilt_deg of up0 holds 3 points."""
    if len(points) < 3:
        return None
    rng = np.random.default_rng(seed)
    best, best_count = None, 2
    cos_limit = math.cos(math.radians(max_tilt_deg))
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) < 1e-9:
            continue
        normal /= np.linalg.norm(normal)
        normal *= np.sign(normal @ up0) or 1.0
        if normal @ up0 < cos_limit:
            continue
        inliers = np.abs(points @ normal - normal @ a) < threshold
        if inliers.sum() > best_count:
            best, best_count = inliers, int(inliers.sum())
    if best is None:
        return None
    for _ in range(3):                                   # least squares on the inliers, then again
        centre = points[best].mean(0)
        normal = np.linalg.svd(points[best] - centre)[2][-1]
        normal *= np.sign(normal @ up0) or 1.0
        best = np.abs((points - centre) @ normal) < threshold
        if best.sum() < 3:
            return None
    return normal, float(-normal @ centre), best


def estimate_camera(joints: list[torch.Tensor], keypoints: list[torch.Tensor], fps: float,
                    pitch_deg: float | None = None, camera_height: float | None = None,
                    min_spread: float = 0.15, max_pitch_deg: float = 60.0,
                    image_pose: CameraPose | None = None) -> CameraPose:
    """The static camera's pose from people in its frame (module docstring).

    joints: per segment (T, 22, 3) joints, camera frame, metres (root included); keypoints: per
    segment (T, 21, 3) the detector's keypoints on the body likewise; fps: their frame rate.
    pitch_deg / camera_height: known values (degrees below the horizon / metres), used as given.
    People whose axes put the camera's pitch or roll past max_pitch_deg are no guide: the camera is
    then taken as level ("level"), as it is when nobody stands.
    image_pose: the pose found from upright people in the image alone
    (humotion.capture.metrology.camera_from_people), when it was: it wins over the lifted people
    (step 0 of the module docstring); a given pitch or camera height still wins over it.
    """
    if image_pose is not None and pitch_deg is None:
        height = image_pose.height if camera_height is None else float(camera_height)
        return CameraPose(image_pose.up.float(), float(height), image_pose.source, image_pose.contacts)
    axes = torch.cat([standing_axes(j) for j in joints]) if joints else torch.zeros(0, 3)
    frames = sum(len(j) for j in joints)
    up0 = median_direction(axes) if len(axes) >= min(MIN_STANDING, max(1, frames // 5)) else None
    if up0 is not None and float(up0 @ torch.tensor(LEVEL_UP)) < math.cos(math.radians(max_pitch_deg)):
        up0 = None                      # the people are no guide (upside down, lying): a level camera
    source = "people" if up0 is not None else "level"
    up0 = up0 if up0 is not None else torch.tensor(LEVEL_UP)
    if pitch_deg is not None:
        up0, source = up_from_pitch(pitch_deg), "given"
    soles = [k[:, SOLES] for k in keypoints]
    touching = [s[contact_soles(s, up0, fps)] for s in soles]
    points = torch.cat(touching).double().numpy() if touching else np.zeros((0, 3))
    up, height, spread = up0, None, 0.0
    fit = fit_floor(points, up0.double().numpy()) if pitch_deg is None else None
    if fit is not None:
        normal, offset, inliers = fit
        on = points[inliers]
        values, vectors = np.linalg.eigh(np.cov((on - on.mean(0)).T)) if len(on) > 3 else (np.zeros(3), np.eye(3))
        spread = float(np.sqrt(max(values[1], 0.0)))
        if spread >= min_spread and offset > 0:
            up, height, source = torch.as_tensor(normal, dtype=torch.float32), offset, "floor"
        elif np.sqrt(max(values[2], 0.0)) >= 2 * min_spread:
            # contacts along one line (a walk there and back): the floor holds that line, so up is
            # made square to it; the people's axes give the rest
            line = vectors[:, 2]
            turned = up0.double().numpy() - (up0.double().numpy() @ line) * line
            up, source = torch.as_tensor(turned / np.linalg.norm(turned), dtype=torch.float32), "people and floor line"
    if height is None:                  # the floor under each frame's lowest point, median over frames
        lowest = [torch.cat([j, k], 1).matmul(up).amin(1).neg() for j, k in zip(joints, keypoints)]
        height = float(torch.cat(lowest).median()) if lowest else 1.5
    if camera_height is not None:
        height = float(camera_height)
    return CameraPose(up.float(), float(height), source, len(points), spread)


def floor_drift(pose: CameraPose, soles: list[torch.Tensor], times: list[torch.Tensor], fps: float,
                window_s: float = 3.0, min_points: int = 12) -> float | None:
    """Largest change (metres) of the floor's distance from the camera between time windows of
    window_s seconds, each fitted on its own contact soles (the pose's up kept): near 0 for a
    static camera. None when fewer than two windows have min_points contact soles.
    soles: per segment (T, 4, 3) camera frame; times: per segment (T,) seconds (float64, or array-like)."""
    heights: dict[int, list[float]] = {}
    for s, t in zip(soles, times):
        contact = contact_soles(s, pose.up, fps)
        distance = -(s @ pose.up)
        for window in np.unique((np.asarray(t) // window_s).astype(int)):
            rows = torch.as_tensor((np.asarray(t) // window_s).astype(int) == window)
            heights.setdefault(int(window), []).extend(distance[rows][contact[rows]].tolist())
    medians = [float(np.median(h)) for h in heights.values() if len(h) >= min_points]
    return max(medians) - min(medians) if len(medians) >= 2 else None


def tilt_correction(joints: torch.Tensor, up: torch.Tensor, max_deg: float = 30.0) -> torch.Tensor:
    """(3, 3) the smallest rotation taking the person's median standing axis (standing_axes of
    joints (T, 22, 3), camera frame) onto up; the identity when they stand on too few frames
    (MIN_STANDING, or a fifth of them) or the turn would exceed max_deg (then they are not
    standing upright, or not on this floor)."""
    axes = standing_axes(joints)
    axis = median_direction(axes) if len(axes) >= min(MIN_STANDING, max(1, len(joints) // 5)) else None
    if axis is None:
        return torch.eye(3)
    cos = float((axis * up).sum().clamp(-1, 1))
    if math.degrees(math.acos(cos)) > max_deg:
        return torch.eye(3)
    return rot.rotation_matrix_between(axis, up)
