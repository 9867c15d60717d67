"""Synthetic 2D keypoints from 3D motion: where a detector's keypoints sit on the canonical body,
virtual pinhole cameras that film it, and a detector-like noise model.

This makes the lifting network's training inputs (specs/video-capture.md, steps 2-4): canonical
mocap -> :func:`body_keypoints_3d` -> :func:`random_camera` -> :meth:`VirtualCamera.project` ->
:func:`corrupt` -> :func:`humotion.capture.lifting.normalise`. Keypoints follow humotion's
detector layout :data:`~humotion.capture.detection.KEYPOINTS` (COCO's 17, heels, big toes).

Where the keypoints sit. Shoulders, elbows, wrists, hips, knees and ankles are the canonical
joints of those names. The face points and the feet's are rigid offsets in a joint's frame (the
canonical rest axes: x the person's left, y up, z forward), in shares of the standing height H
(:meth:`Skeleton.height`, whose top is the head_top end site), from adult anthropometry. Face,
from the top of the head along the head's axes: the eyes at Drillis & Contini's eye level 0.936
H (as tabulated by Winter, Biomechanics and Motor Control of Human Movement, 2009), so 0.064 H
below the top, 63 mm apart (the adult mean interpupillary distance, Dodgson 2004: 0.037 H at
1.70 m) and 0.050 H (8.5 cm) in front of the ear canals; the ears half a head breadth (0.089 H,
about 15 cm) to each side, level with the lower eye rims (the Frankfurt plane, 0.008 H below the
pupils), straight below the top of the head; the nose tip 0.022 H below the eyes and 0.015 H in
front of them. Feet: the heel point (the back of the heel) 0.034 H behind the ankle, Winter's
foot length 0.152 H less the canonical template's 0.118 H from ankle to toe tip, and 0.030 H
below it (1.5 cm above the sole, the ankle being 0.039 H high); the big toe tip is the skeleton's
toe end site moved 0.014 H towards the body's midline (a quarter of Winter's foot breadth 0.055
H). These are estimates: detectors disagree among themselves by more (BlazePose's hips, for one,
are not COCO's), which the noise model's per-keypoint biases stand for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.capture.detection import KEYPOINTS
from humotion.skeleton import Skeleton, counterpart_indices

# Offsets in shares of standing height (module docstring): face points from the head_top end site
# in the head's frame, the heel from the ankle in the ankle's frame.
_FACE = {
    "nose": (0.0, -0.086, 0.065),
    "left_eye": (0.0185, -0.064, 0.050), "right_eye": (-0.0185, -0.064, 0.050),
    "left_ear": (0.0445, -0.072, 0.0), "right_ear": (-0.0445, -0.072, 0.0),
}
_HEEL = (0.0, -0.030, -0.034)
_BIG_TOE_INWARDS = 0.014

KEYPOINT_MIRROR: tuple[int, ...] = tuple(int(i) for i in counterpart_indices(KEYPOINTS))
"""For each keypoint the index of its left/right counterpart (itself for the nose)."""


def keypoint_anchors(skeleton: Skeleton) -> tuple[list[int], torch.Tensor]:
    """Per keypoint (KEYPOINTS order) the canonical joint it moves with and its offset (21, 3) in
    that joint's frame, metres (float64), for a canonical skeleton with toe end sites."""
    if tuple(skeleton.names) != JOINTS:
        raise ValueError("keypoints need a skeleton on the canonical joints (humotion.canonical.JOINTS); "
                         "map the motion first with humotion.canonical.to_canonical")
    missing = [name for name in ("head_top", "left_toe", "right_toe") if name not in skeleton.end_site_names]
    if missing:
        raise ValueError(f"the skeleton lacks the end sites {missing} that place the face and the big toes")
    height = skeleton.height()

    def end_site(name: str) -> torch.Tensor:
        return skeleton.end_site_offsets[skeleton.end_site_names.index(name)].double()

    def vector(values) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.float64)

    joints, offsets = [], []
    for name in KEYPOINTS:
        side, sign = ("left", 1.0) if name.startswith("left_") else ("right", -1.0)
        if name in JOINTS:
            joints.append(JOINTS.index(name))
            offsets.append(vector([0.0, 0.0, 0.0]))
        elif name in _FACE:
            joints.append(JOINTS.index("head"))
            offsets.append(end_site("head_top") + vector(_FACE[name]) * height)
        elif name.endswith("_heel"):
            joints.append(JOINTS.index(f"{side}_ankle"))
            offsets.append(vector(_HEEL) * height)
        else:  # big toe: the toe end site, moved towards the midline (-x on the left foot)
            joints.append(JOINTS.index(f"{side}_foot"))
            offsets.append(end_site(f"{side}_toe") + vector([-sign * _BIG_TOE_INWARDS * height, 0.0, 0.0]))
    return joints, torch.stack(offsets)


def body_keypoints_3d(world_rotations: torch.Tensor, world_positions: torch.Tensor, skeleton: Skeleton,
                      anchors: tuple[list[int], torch.Tensor] | None = None) -> torch.Tensor:
    """(..., 21, 3) world positions (metres) of the detector keypoints on the canonical body.

    world_rotations: (..., 22, 3, 3) joint-to-world rotations; world_positions: (..., 22, 3)
    metres (as Motion.world() gives them); skeleton: the motion's canonical skeleton (its height
    scales the face and foot offsets; its head_top and toe end sites place the face and big toes).
    anchors: keypoint_anchors(skeleton), when the caller already has them (an optimisation loop).
    """
    if world_rotations.shape[-3:] != (len(JOINTS), 3, 3) or world_positions.shape[-2:] != (len(JOINTS), 3):
        raise ValueError(f"expected world rotations (..., {len(JOINTS)}, 3, 3) and positions (..., {len(JOINTS)}, 3), "
                         f"got {tuple(world_rotations.shape)} and {tuple(world_positions.shape)}")
    joints, offsets = keypoint_anchors(skeleton) if anchors is None else anchors
    offsets = offsets.to(world_positions.dtype)
    return world_positions[..., joints, :] + (world_rotations[..., joints, :, :] @ offsets[:, :, None])[..., 0]


# -- cameras -------------------------------------------------------------------------------

@dataclass
class VirtualCamera:
    """Pinhole cameras without lens distortion: one, or a batch of shape C.

    Camera frame: OpenCV's, x right, y down, z forward along the optical axis. A world point p
    (metres; humotion's world has Y up) is at rotation @ p + translation in the camera frame and
    projects to the pixel (fx x / z + cx, fy y / z + cy), measured from the image's top-left
    corner (the image spans [0, width] x [0, height], as in Detection.keypoints).

    fx, fy: focal lengths, pixels (C). cx, cy: principal point, pixels (C). width, height: image
    size, pixels (C). rotation: (*C, 3, 3) world to camera. translation: (*C, 3) metres.
    """

    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor

    def __post_init__(self):
        for f in fields(self):
            setattr(self, f.name, torch.as_tensor(getattr(self, f.name), dtype=torch.float32))
        batch = self.fx.shape
        if self.rotation.shape != batch + (3, 3) or self.translation.shape != batch + (3,):
            raise ValueError(f"camera batch shape {tuple(batch)} needs rotation {tuple(batch) + (3, 3)} and "
                             f"translation {tuple(batch) + (3,)}, got {tuple(self.rotation.shape)} and "
                             f"{tuple(self.translation.shape)}")

    @classmethod
    def looking_at(cls, eye, target, hfov_deg: float, width: int, height: int) -> VirtualCamera:
        """One level camera (no roll) at `eye` looking at `target` (world points, metres), with the
        principal point at the image centre and square pixels."""
        fx = width / 2 / math.tan(math.radians(hfov_deg) / 2)
        eye, target = torch.as_tensor(eye, dtype=torch.float32), torch.as_tensor(target, dtype=torch.float32)
        rotation = look_at_rotation(eye, target)
        translation = -(rotation @ eye)
        return cls(fx, fx, width / 2, height / 2, width, height, rotation, translation)

    @property
    def size(self) -> torch.Tensor:
        """(*C, 2) image width and height, pixels."""
        return torch.stack([self.width, self.height], dim=-1)

    @property
    def position(self) -> torch.Tensor:
        """(*C, 3) the camera's centre in the world, metres."""
        return -(self.rotation.transpose(-1, -2) @ self.translation[..., None])[..., 0]

    def _per_point(self, value: torch.Tensor, points: torch.Tensor, trailing: int) -> torch.Tensor:
        """value (*C, *trailing dims) reshaped to broadcast against points (*C, *S, 3)."""
        extra = points.dim() - 1 - self.fx.dim()
        if extra < 0 or points.shape[:self.fx.dim()] != self.fx.shape or points.shape[-1] != 3:
            raise ValueError(f"points must have shape (*C, ..., 3) with the camera batch C = {tuple(self.fx.shape)}, "
                             f"got {tuple(points.shape)}")
        return value.reshape(self.fx.shape + (1,) * extra + value.shape[value.dim() - trailing:])

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(*C, *S, 3) world points (metres) in the camera frame (x right, y down, z forward)."""
        points = torch.as_tensor(points, dtype=torch.float32)
        rotation = self._per_point(self.rotation, points, 2)
        return (rotation @ points[..., None])[..., 0] + self._per_point(self.translation, points, 1)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(pixels (*C, *S, 2), depth (*C, *S) metres along the optical axis) of (*C, *S, 3) world
        points. Points at depth <= 0 (behind the camera) get meaningless, finite pixels."""
        local = self.to_camera(points)
        depth = local[..., 2]
        z = depth.clamp_min(1e-6)

        def per_point(value):
            return self._per_point(value, points, 0)

        pixels = torch.stack([per_point(self.fx) * local[..., 0] / z + per_point(self.cx),
                              per_point(self.fy) * local[..., 1] / z + per_point(self.cy)], dim=-1)
        return pixels, depth


def look_at_rotation(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) world-to-camera rotation of level cameras at eye (..., 3) looking at target
    (..., 3): rows are the camera's right, down and forward directions in the world (Y up)."""
    forward = torch.nn.functional.normalize(target - eye, dim=-1)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=forward.dtype).expand_as(forward)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=-1)
    down = torch.linalg.cross(forward, right)
    return torch.stack([right, down, forward], dim=-2)


@dataclass(frozen=True)
class CameraRanges:
    """What :func:`random_camera` draws from, uniformly.

    distance: metres, horizontal, from the camera to the centre of the person's box (raised where
        the person would not fit). height: metres above the person's lowest point (the floor):
        from a camera on a table or the floor to one held high. hfov_deg: horizontal field of view,
        from a mild telephoto to a wide webcam or phone lens. sizes: (width, height) pixels of
        common video (VGA webcams, 4:3 and 16:9 HD). roll_deg: the horizon tilted by up to this
        (hand-held or unlevelled cameras). fill: at the nearest distance the person's box takes at
        most this share of the image's width and height. aim: the person is aimed off the optical
        axis by up to this share of the angle left free around them. principal_offset: the
        principal point lies up to this share of the image size from its centre (an assumption
        for consumer cameras, which report principal points near the centre).
    """

    distance: tuple[float, float] = (2.5, 8.0)
    height: tuple[float, float] = (0.3, 2.2)
    hfov_deg: tuple[float, float] = (45.0, 90.0)
    sizes: tuple[tuple[int, int], ...] = ((640, 480), (1280, 960), (1280, 720), (1920, 1080))
    roll_deg: float = 5.0
    fill: float = 0.8
    aim: float = 0.5
    principal_offset: float = 0.02


def random_camera(generator: torch.Generator, points: torch.Tensor,
                  ranges: CameraRanges = CameraRanges()) -> VirtualCamera:
    """Random cameras that film a person, one per batch item.

    points: (B, N, 3) or (N, 3) world points of the person (metres, Y up), e.g. every joint and
    keypoint of every frame of a window: the camera looks at the centre of their box from a
    random direction (any yaw), at a distance where the whole box fits the image (see
    CameraRanges.fill), so the person stays mostly inside the frame. generator: a CPU generator.
    Returns a VirtualCamera of batch shape (B,) (or () for (N, 3) points).
    """
    points = torch.as_tensor(points, dtype=torch.float32)
    single = points.dim() == 2
    points = points[None] if single else points
    if points.dim() != 3 or points.shape[-1] != 3 or points.shape[1] == 0:
        raise ValueError(f"points must have shape (B, N, 3) or (N, 3), got {tuple(points.shape)}")
    b = points.shape[0]

    def uniform(low, high):
        return low + (high - low) * torch.rand(b, generator=generator)

    sizes = torch.tensor(ranges.sizes, dtype=torch.float32)[torch.randint(len(ranges.sizes), (b,), generator=generator)]
    width, height = sizes.unbind(-1)
    tan_h = torch.tan(torch.deg2rad(uniform(*ranges.hfov_deg)) / 2)
    focal = width / 2 / tan_h
    tan_v = height / 2 / focal
    cx = width * (0.5 + ranges.principal_offset * uniform(-1.0, 1.0))
    cy = height * (0.5 + ranges.principal_offset * uniform(-1.0, 1.0))

    low, high = points.amin(1), points.amax(1)
    centre, extent = (low + high) / 2, high - low
    radius = extent[:, [0, 2]].norm(dim=-1) / 2          # horizontal half-diagonal: fits any yaw
    fit = torch.maximum(extent[:, 1] / (2 * tan_v), radius / tan_h) / ranges.fill + radius
    near = torch.maximum(fit, torch.tensor(ranges.distance[0]))
    far = torch.maximum(fit, torch.tensor(ranges.distance[1]))
    distance = near + (far - near) * torch.rand(b, generator=generator)
    azimuth = uniform(0.0, 2 * math.pi)
    eye = torch.stack([centre[:, 0] + distance * torch.sin(azimuth), low[:, 1] + uniform(*ranges.height),
                       centre[:, 2] + distance * torch.cos(azimuth)], dim=-1)

    # Aim off-centre within the angle the person leaves free, and tilt the horizon.
    nearest = (distance - radius).clamp_min(1e-3)
    free_h = (torch.atan(tan_h) - torch.atan(radius / nearest)).clamp_min(0)
    free_v = (torch.atan(tan_v) - torch.atan(extent[:, 1] / 2 / nearest)).clamp_min(0)
    pan, tilt = ranges.aim * free_h * uniform(-1.0, 1.0), ranges.aim * free_v * uniform(-1.0, 1.0)
    roll = torch.deg2rad(uniform(-ranges.roll_deg, ranges.roll_deg))
    zero = torch.zeros(b)
    turn = (rot.convert(torch.stack([zero, zero, roll], -1), "rotvec", "matrix")
            @ rot.convert(torch.stack([tilt, zero, zero], -1), "rotvec", "matrix")
            @ rot.convert(torch.stack([zero, pan, zero], -1), "rotvec", "matrix"))
    rotation = turn @ look_at_rotation(eye, centre)
    translation = -(rotation @ eye[..., None])[..., 0]
    camera = VirtualCamera(focal, focal, cx, cy, width, height, rotation, translation)
    if single:
        camera = VirtualCamera(*(getattr(camera, f.name)[0] for f in fields(camera)))
    return camera


# -- detector noise ------------------------------------------------------------------------

KEYPOINT_SIGMAS: tuple[float, ...] = (
    0.026, 0.025, 0.025, 0.035, 0.035, 0.079, 0.079, 0.072, 0.072, 0.062, 0.062,
    0.107, 0.107, 0.087, 0.087, 0.089, 0.089, 0.080, 0.080, 0.080, 0.080,
)  # fmt: skip
"""Per keypoint, how far people clicking the same keypoint disagree: the standard deviation as a
share of the person's scale s (the square root of their segmented area). COCO's keypoint
evaluation constants (the OKS sigmas of Lin et al. 2014, cocodataset.org), and for heels and big
toes COCO-WholeBody's (Jin et al., ECCV 2020), whose published left (0.066, 0.068) and right
(0.094, 0.092) values are averaged here so that neither side is noisier."""

SWAP_GROUPS: tuple[tuple[str, ...], ...] = (
    ("eye", "ear"), ("elbow", "wrist"), ("knee", "ankle", "heel", "big_toe"))
"""Parts a detector mixes up as a whole between left and right (its "inversions")."""

MIN_DEPTH = 0.1
"""Metres: keypoints nearer the camera than this (or behind it) are missing."""


@dataclass(frozen=True)
class DetectorNoise:
    """How :func:`corrupt` spoils perfect keypoints, in the manner of a 2D pose detector.

    Displacements are in units of KEYPOINT_SIGMAS[k] * s (s: the person's scale in pixels, the
    square root of the area of the keypoints' box, which stands in for COCO's segmented area).
    A detector whose per-axis error is sigma * s scores an expected OKS of 0.8 per keypoint, about
    what good COCO detectors reach; that error is split here, by assumption, into a per-window
    bias (0.6: a detector's own idea of where a joint is, which lasts while the pose and view do)
    and per-frame jitter (0.8), since 0.6^2 + 0.8^2 = 1.
    outliers: chance per keypoint and frame of a gross error (a point anywhere in the person's box,
    with lower confidence); swaps: chance per frame and SWAP_GROUPS entry of a left/right
    inversion; dropout: chance per keypoint and frame that the detector gives nothing; frame_drops:
    chance that a whole frame has no person; occluders: chance per window of a box in front of the
    person (a side between occluder_size shares of the person's box; keypoints behind it are
    missing half the time, else displaced by 2 more sigmas and given confidence up to
    occluded_confidence). These rates are assumptions of the order of the error types counted by
    Ruggero Ronchi & Perona (ICCV 2017, "Benchmarking and error diagnosis in multi-instance pose
    estimation"), not measurements. confidence: the range a well-seen keypoint's confidence is drawn
    from; outlier_confidence: the range for gross errors (overlapping, as real confidences do).
    """

    bias: float = 0.6
    jitter: float = 0.8
    outliers: float = 0.01
    swaps: float = 0.01
    dropout: float = 0.02
    frame_drops: float = 0.01
    occluders: float = 0.3
    occluder_size: tuple[float, float] = (0.2, 0.5)
    occluded_confidence: float = 0.3
    confidence: tuple[float, float] = (0.5, 1.0)
    outlier_confidence: tuple[float, float] = (0.1, 0.7)

    @classmethod
    def none(cls) -> DetectorNoise:
        """No noise at all: corrupt() then only marks keypoints outside the image as missing."""
        return cls(bias=0.0, jitter=0.0, outliers=0.0, swaps=0.0, dropout=0.0, frame_drops=0.0, occluders=0.0,
                   confidence=(1.0, 1.0))


def corrupt(pixels: torch.Tensor, generator: torch.Generator, noise: DetectorNoise = DetectorNoise(),
            image_size: torch.Tensor | None = None,
            depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Detector-like keypoints and confidences from perfect ones.

    pixels: (..., T, 21, 2) true keypoint pixels of windows of T frames (one person, one camera
    per window: biases and occluders last a window). generator: a CPU generator.
    image_size: (..., 2) width and height in pixels: keypoints outside the image are missing.
    depth: (..., T, 21) metres along the optical axis: keypoints nearer than MIN_DEPTH are missing.
    Returns (pixels (..., T, 21, 2), confidence (..., T, 21) in [0, 1], 0 for a missing keypoint,
    whose pixels are then meaningless). DetectorNoise.none() gives the pixels back unchanged.
    """
    pixels = torch.as_tensor(pixels, dtype=torch.float32)
    k = len(KEYPOINTS)
    if pixels.dim() < 3 or pixels.shape[-2:] != (k, 2):
        raise ValueError(f"pixels must have shape (..., T, {k}, 2), got {tuple(pixels.shape)}")
    frames = pixels.shape[:-2]                    # (..., T)
    windows = pixels.shape[:-3] + (1,)            # (..., 1): one draw per window

    def rand(shape):
        return torch.rand(shape, generator=generator)

    def uniform(shape, bounds):
        return bounds[0] + (bounds[1] - bounds[0]) * rand(shape)

    def normal(shape):
        return torch.randn(shape, generator=generator)

    low, high = pixels.amin(-2, keepdim=True), pixels.amax(-2, keepdim=True)       # (..., T, 1, 2)
    box = high - low
    scale = box.prod(-1, keepdim=True).sqrt().clamp_min(1.0)                      # (..., T, 1, 1)
    sigma = torch.tensor(KEYPOINT_SIGMAS)[:, None]
    noisy = (pixels + noise.bias * sigma * scale.mean(-3, keepdim=True) * normal(windows + (k, 2))
             + noise.jitter * sigma * scale * normal(frames + (k, 2)))
    confidence = uniform(frames + (k,), noise.confidence)

    for parts in SWAP_GROUPS:
        group = [i for i, name in enumerate(KEYPOINTS) if name.split("_", 1)[-1] in parts]
        swapped = (rand(frames) < noise.swaps)[..., None, None]
        noisy[..., group, :] = torch.where(swapped, noisy[..., [KEYPOINT_MIRROR[i] for i in group], :],
                                           noisy[..., group, :])

    outlier = rand(frames + (k,)) < noise.outliers
    anywhere = low - 0.05 * box + 1.1 * box * rand(frames + (k, 2))
    noisy = torch.where(outlier[..., None], anywhere, noisy)
    confidence = torch.where(outlier, uniform(frames + (k,), noise.outlier_confidence), confidence)

    window_low, window_box = low.mean(-3, keepdim=True), box.mean(-3, keepdim=True)   # (..., 1, 1, 2)
    size = window_box * uniform(windows + (1, 2), noise.occluder_size)
    corner = window_low + (window_box - size) * rand(windows + (1, 2))
    occluded = (((noisy >= corner) & (noisy <= corner + size)).all(-1)
                & (rand(windows + (1,)) < noise.occluders))                           # (..., T, 21)
    noisy = noisy + occluded[..., None] * 2 * sigma * scale * normal(frames + (k, 2))
    confidence = torch.where(occluded, uniform(frames + (k,), (0.0, noise.occluded_confidence)), confidence)

    missing = (rand(frames + (k,)) < noise.dropout) | (rand(frames + (1,)) < noise.frame_drops)
    missing |= occluded & (rand(frames + (k,)) < 0.5)
    if image_size is not None:
        size = torch.as_tensor(image_size, dtype=torch.float32)[..., None, None, :]
        missing |= ((noisy < 0) | (noisy > size)).any(-1)
    if depth is not None:
        missing |= torch.as_tensor(depth) < MIN_DEPTH
    return noisy, torch.where(missing, 0.0, confidence)
