"""The camera's horizon and height from upright people in the image (single-view metrology).

    pose = camera_from_people(segments_keypoints, segments_confidence, heights, camera)

A person standing or walking upright is a vertical segment of known height standing on the floor:
their image alone, over many frames and places, fixes the camera's pitch, roll and height above
the floor, without any 3D lifting (Hoiem, Efros and Hebert 2006, "Putting objects in
perspective"; Criminisi, Reid and Zisserman 2000, "Single view metrology"). Where people stand
nearer or farther, higher or lower in the image, their image heights and the convergence of
their vertical axes tell the horizon and the camera's height in units of their height.

Model (camera frame: OpenCV's, x right, y down, z forward; intrinsics known): the floor's up
direction u (unit) and the camera's height h. On an upright frame of a person of height H, the
midpoints of their ankles, hips and shoulders lie on one vertical line at the heights k H above
the floor where detectors mark them on a standing person (LANDMARK_LEVELS). The ankles' midpoint
seen at pixel a is the point X = s d on the ray d through a with u . X + h = k_ankle H; the
hips' and shoulders' midpoints are predicted at X + (k - k_ankle) H u, projected. (u, h)
minimise the robust (soft L1) sum of the differences between predicted and seen midpoints, in
units of the person's image height (ankles to shoulders), over every upright frame of the video.

Upright frames are chosen in the image alone: ankles, knees, hips and shoulders seen with
confidence, each leg straight in the image (hip, knee and ankle in line within 20 degrees), the
ankles', hips' and shoulders' midpoints in line within 20 degrees (a straight 3D line stays
straight in the image) and the body within 45 degrees of the image's vertical. Walking people
lean a few degrees; the robust loss and the many frames carry that.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from humotion.capture.camera import CameraPose
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import VirtualCamera

_K = {name: i for i, name in enumerate(KEYPOINTS)}
_PAIRS = (("left_ankle", "right_ankle"), ("left_hip", "right_hip"), ("left_shoulder", "right_shoulder"))
MIN_UPRIGHT = 20
"""Upright observations needed before the image is trusted."""


LANDMARK_LEVELS = (0.039, 0.530, 0.818)
"""Heights above the floor, as shares of stature, of the ankles', hips' and shoulders' landmarks
that a 2D detector marks on a standing person: the ankle (lateral malleolus), the hip (greater
trochanter) and the shoulder (acromion), from anthropometry (Winter, Biomechanics and Motor
Control of Human Movement, after Drillis and Contini 1966). The template body's joint centres
(0.041, 0.518, 0.824 of its height) are not where detectors put their points, and with few people
at one place the fitted pitch follows these ratios closely (5% on the hips moves it by 12-14
degrees): with the joint centres the Intel clip's camera came out 29 degrees down where the
room's floorboards and window edges say 34-38, with these 37.6."""


def standing_levels(height_m: float = 1.0) -> np.ndarray:
    """(3,) heights above the floor (metres) of the ankles', hips' and shoulders' midpoints of a
    person height_m tall standing (LANDMARK_LEVELS)."""
    return np.array(LANDMARK_LEVELS) * height_m


def upright_midpoints(keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.3,
                      max_bend_deg: float = 20.0, max_tilt_deg: float = 45.0, min_pixels: float = 20.0) -> np.ndarray:
    """(N, 3, 2) pixels of the ankles', hips' and shoulders' midpoints on the frames of one
    person's keypoints (T, 21, 2) with confidence (T, 21) where they look upright (module
    docstring); N <= T."""
    names = [n for pair in _PAIRS for n in pair] + ["left_knee", "right_knee"]
    seen = (confidence[:, [_K[n] for n in names]] >= min_confidence).all(1)
    mids = np.stack([(keypoints[:, _K[a]] + keypoints[:, _K[b]]) / 2 for a, b in _PAIRS], 1)   # (T, 3, 2)
    cos_bend = math.cos(math.radians(180.0 - max_bend_deg))

    def straight(a, b, c):          # the angle at b between a and c is near 180 degrees
        u, v = a - b, c - b
        return (u * v).sum(-1) < cos_bend * np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1)

    ok = seen & straight(mids[:, 0], mids[:, 1], mids[:, 2])
    for side in ("left", "right"):
        ok &= straight(keypoints[:, _K[f"{side}_hip"]], keypoints[:, _K[f"{side}_knee"]], keypoints[:, _K[f"{side}_ankle"]])
    axis = mids[:, 0] - mids[:, 2]                                  # shoulders to ankles: down the image
    length = np.linalg.norm(axis, axis=-1)
    ok &= (length >= min_pixels) & (axis[:, 1] > math.cos(math.radians(max_tilt_deg)) * length)
    return mids[ok]


def _up(params: np.ndarray) -> np.ndarray:
    """The floor's unit up direction in the camera frame from (a, b): up along (a, -1, -b)."""
    up = np.array([params[0], -1.0, -params[1]])
    return up / np.linalg.norm(up)


def _rays(params: np.ndarray, mids: np.ndarray, levels: np.ndarray, camera: tuple):
    """(rays (N, 3) through the ankles' midpoints, their component along up (N,), the distance
    (N,) along each ray to the ankles' height over the floor, up (3,))."""
    fx, fy, cx, cy = camera
    up, h = _up(params), math.exp(params[2])
    ray = np.stack([(mids[:, 0, 0] - cx) / fx, (mids[:, 0, 1] - cy) / fy, np.ones(len(mids))], 1)
    along = ray @ up                                                   # < 0: the ray goes down
    return ray, along, (levels[:, 0] - h) / np.minimum(along, -1e-3), up


def _residuals(params: np.ndarray, mids: np.ndarray, levels: np.ndarray, camera: tuple) -> np.ndarray:
    """(N * 4,) predicted minus seen hips' and shoulders' midpoints (x, y), in units of each
    person's image height (ankles to shoulders)."""
    fx, fy, cx, cy = camera
    ray, along, scale, up = _rays(params, mids, levels, camera)
    ankle = scale[:, None] * ray
    size = np.linalg.norm(mids[:, 0] - mids[:, 2], axis=-1)
    out = []
    for k in (1, 2):
        point = ankle + (levels[:, k] - levels[:, 0])[:, None] * up
        depth = np.maximum(point[:, 2], 1e-3)
        pixel = np.stack([fx * point[:, 0] / depth + cx, fy * point[:, 1] / depth + cy], 1)
        out.append((pixel - mids[:, k]) / size[:, None])
    bad = (along > -1e-3) | (scale <= 0)                              # ankles above the horizon: no floor there
    residual = np.concatenate(out, 1)
    residual[bad] = 1.0
    return residual.ravel()


def camera_from_people(keypoints: list[np.ndarray], confidence: list[np.ndarray], heights: list[float],
                       camera: VirtualCamera, max_observations: int = 3000, max_pitch_std_deg: float = 5.0,
                       max_height_cv: float = 0.05) -> CameraPose | None:
    """The static camera's pose (source "people in the image") from people's 2D keypoints alone
    (module docstring), or None when fewer than MIN_UPRIGHT upright frames are seen or the fit
    leaves the pitch or roll unsure by over max_pitch_std_deg (one standard deviation) or the
    height by over max_height_cv of itself (people seen at one place only: the height then
    trades against the pitch; the limits are tight because the deviations, from the noise alone,
    leave out the people's lean and proportions). The pitch's limit is loose: on a short clip of
    a few people (the shared aisle clip, 25 upright frames) the fit is unsure by about 3 degrees,
    and the floor of the lifted people's feet, the fallback, was 28 degrees off there.

    keypoints: per segment (T, 21, 2) pixels; confidence: per segment (T, 21); heights: per
    segment the person's standing height (metres); camera: the intrinsics."""
    parts = [(upright_midpoints(k, c), h) for k, c, h in zip(keypoints, confidence, heights)]
    mids = np.concatenate([m for m, _ in parts]) if parts else np.zeros((0, 3, 2))
    if len(mids) < MIN_UPRIGHT:
        return None
    levels = np.concatenate([np.repeat(standing_levels(h)[None], len(m), 0) for m, h in parts])
    if len(mids) > max_observations:                                   # evenly thinned: the fit costs per point
        keep = np.linspace(0, len(mids) - 1, max_observations).round().astype(int)
        mids, levels = mids[keep], levels[keep]
    intrinsics = tuple(float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    scale = 0.02                                                       # soft L1 knee: 2% of the person's height

    def cost(params):
        r = _residuals(params, mids, levels, intrinsics)
        return float(np.sum(2 * (np.sqrt(1 + (r / scale) ** 2) - 1)))

    from scipy.optimize import least_squares   # here: scipy.optimize costs every `humotion` start 0.4 s

    starts = [np.array([0.0, math.tan(math.radians(p)), math.log(h)])
              for p in (-10.0, 0.0, 10.0, 20.0, 30.0, 45.0, 60.0) for h in (1.0, 2.0, 4.0, 8.0)]
    start = min(starts, key=cost)
    fit = least_squares(_residuals, start, args=(mids, levels, intrinsics), loss="soft_l1", f_scale=scale,
                        x_scale=np.array([0.1, 0.1, 0.1]))
    std = _standard_deviations(fit)
    if std is None:
        return None
    up = _up(fit.x)
    pose = CameraPose(torch.as_tensor(up, dtype=torch.float32), math.exp(fit.x[2]), "people in the image", len(mids))
    angle_std = math.degrees(max(std[0], std[1]) * up[1] ** 2)         # d(angle)/d(a or b): cos^2 of the pitch
    if angle_std > max_pitch_std_deg or std[2] > max_height_cv or abs(pose.pitch_deg) > 80.0:
        return None
    return pose


def _standard_deviations(fit) -> np.ndarray | None:
    """(3,) standard deviations of the fitted parameters from the Jacobian at the solution (the
    residuals' robust scale as the noise), or None when they are not determined."""
    jacobian = fit.jac
    sigma2 = float(np.median(fit.fun ** 2)) / 0.455                    # median of chi2(1) is 0.455
    try:
        covariance = np.linalg.inv(jacobian.T @ jacobian) * sigma2
    except np.linalg.LinAlgError:
        return None
    diagonal = np.diag(covariance)
    return np.sqrt(diagonal) if np.all(diagonal >= 0) else None
