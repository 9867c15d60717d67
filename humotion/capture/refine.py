"""Refinement of one person's lifted motion against the 2D detections (specs/video-capture.md, step 8).

Minimises, over joint rotations theta (T, 22, 3) rotation vectors (joint 0 global, in the camera
frame) and root positions r (T, 3) metres in the camera frame (OpenCV: x right, y down, z forward),
on the person's fixed template skeleton:

    E = w_key E_key + w_init E_init + w_prior E_prior + w_temporal E_temporal
    E_key      = sum_t,k c_tk rho(|| (pi(X_tk(theta_t) + r_t) - s_tk) / size_t ||^2)
                 reprojection of the detector keypoints placed on the body
                 (humotion.capture.keypoints.body_keypoints_3d) through the camera, against the
                 detected pixels s weighted by their confidences c, in units of the person's 2D size
                 (:func:`person_size`: the diagonal of the box around their confident keypoints),
                 so weights do not depend on the image resolution; rho(e) = 2 b^2 (sqrt(1 + e / b^2) - 1),
                 a pseudo-Huber loss of scale b (CaptureRefineConfig.robust): squares for errors
                 well under b, growing linearly for gross ones (a bounded loss, as Geman-McClure's,
                 lets the foot terms drag a body off its 2D keypoints once they are far);
    E_init     = sum_t,j || S_tj(theta_t) - N_tj ||^2: closeness (metres) to the network's 3D joints
                 N (bone-corrected, pelvis-relative, camera frame);
    E_prior    = sum_t -log G(theta_t; mu, Sigma) (humotion.capture.prior.PosePrior);
    E_temporal = sum_t,j || (S_tj(theta_t) + r_t) - (S_t-1,j(theta_t-1) + r_t-1) ||^2 (metres);
    and, when the floor is known (humotion.capture.camera.CameraPose: up u and camera height h in
    the camera frame), the feet (the sole keypoints: heels and big toes, humotion.capture.camera.SOLES):
    E_floor    = sum over planted soles of (u . p + h)^2, plus over all soles of min(u . p + h, 0)^2:
                 planted soles on the floor, no sole under it (metres);
    E_skate    = sum over soles planted or still on frames t-1 and t of || p_t - p_t-1 ||^2:
                 planted feet do not slide (metres). Planted and still soles: the caller's
                 (humotion.capture.camera.contact_soles, still_soles).
    E_support  = sum_t max(min over soles of (u . p + h) - SUPPORT_TOLERANCE, 0)^2: on every frame
                 some sole stands on the floor, even where none is found planted (a person walking
                 towards the camera, whose soles all move in depth, floated on real clips without
                 it). Running's and jumping's flight phases are pulled down as well.

theta starts from the joint angles of the corrected skeleton (step 7); r from
:func:`initial_root`, the root track that best reprojects the keypoints with a smooth depth (one
linear least-squares solve per segment). Solved with L-BFGS, the energy and its gradient computed
by compiled code (humotion.capture.refine_energy). Bone lengths are the template's on every
frame by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from humotion import rotations as rot
from humotion.capture.camera import SOLES
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d, keypoint_anchors
from humotion.capture.prior import PosePrior
from humotion.optimize import minimise_lbfgs, minimise_lbfgs_with_gradient
from humotion.skeleton import Skeleton, forward_kinematics_by_level

TERMS = ("key", "init", "prior", "temporal", "floor", "skate", "support")
SUPPORT_TOLERANCE = 0.02
"""Metres: E_support lets a frame's lowest sole rise this far above the floor before it pulls."""


@dataclass
class CaptureRefineConfig:
    """Weights of the terms (0 switches a term off; photo_init: E_init's weight for a single
    frame, a photo), E_key's robust scale (a share of the person's 2D size; 0: plain squares),
    L-BFGS iterations per pass (for a segment of several frames, and for a photo), and the image
    speed (m/s at the person) under which a low sole counts as still and is held by E_skate
    (humotion.capture.camera.still_soles; 0: none). compiled: the energy and its gradient from
    compiled code (humotion.capture.refine_energy); False: written in torch and differentiated
    by autograd (:meth:`Terms.energy`, the reference; the same minimum, about 5 times slower).

    still_speed: over the CMU test subjects filmed by random cameras with detector-like noise
    (bench/capture_eval.py), the detector's jitter moves many of the soles the truth plants
    faster than 0.5 m/s in the image; at 0.65 the soles the truth plants slide at 24 against
    29 cm/s, for 0.1 px more reprojection (0.3 on the hand-held hikers clip,
    bench/capture_reprojection.py). iterations: the held soles couple whole stretches of frames,
    which L-BFGS settles slowly: from 75 steps a pass to 150 (cheap since the energy is compiled),
    the soles the truth plants slide at 24 against 29 cm/s and the keypoints reproject within
    10.9 against 12.7 px (median, bench/capture_eval.py); the real clips' reprojection dropped
    by 1.3-2 px (bench/capture_reprojection.py).

    photo_init: a photo has no neighbouring frames, and the lean of a trunk towards or away from
    the camera barely moves its keypoints, so at E_init's weight of 1 the energy's minimum leaned
    the shared standing photos' people by up to 7 degrees where the lifter has them within 3
    (it hid behind stopping L-BFGS early, at 50 steps, which held for some photos and detectors
    and not others); at 3, converged (200 steps), they stay within 4 degrees with either
    detector (tests/test_capture_pipeline.py), their keypoints about as near their detections
    (median 7-13 px against 6-15 with the old settings).

    E_key's weight: with 1, the closeness to the lifter outweighed the detections, and the 3D
    keypoints missed their own 2D keypoints by 7-10 px (median) on real clips; 30 brings that to
    a few pixels (bench/capture_reprojection.py). The robust scale keeps gross 2D errors (swaps,
    outliers) from pulling the body as hard as plain squares would at that weight; E_temporal
    (from 1) and the foot terms (from 1000) rose with it, so the root does not follow the 2D
    jitter in depth and planted soles stay on the floor within 2 cm (tests/test_capture_feet.py)."""

    key: float = 30.0
    init: float = 1.0
    photo_init: float = 3.0
    prior: float = 1e-3
    temporal: float = 4.0
    floor: float = 3000.0
    skate: float = 3000.0
    support: float = 3000.0
    iterations: int = 150
    photo_iterations: int = 200
    robust: float = 0.05
    still_speed: float = 0.65
    compiled: bool = True

    def without(self, term: str) -> "CaptureRefineConfig":
        """A copy with one term switched off (for ablations)."""
        if term not in TERMS:
            raise ValueError(f"unknown refinement term {term!r}; terms are {TERMS}")
        return replace(self, **{term: 0.0})


def intrinsics(camera: VirtualCamera) -> VirtualCamera:
    """The camera with identity extrinsics: points are already in its frame."""
    return VirtualCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                         torch.eye(3), torch.zeros(3))


ROOT_ACCELERATION = 5.0
"""m/s^2: the scale of a person's root acceleration that :func:`initial_root` expects over a
track (walking's bob and sway stay under it; a jump's landing exceeds it briefly)."""
KEYPOINT_NOISE = 0.03
"""Metres at the person: the scale of a 2D keypoint's error that :func:`initial_root` expects."""


def initial_root(relative: torch.Tensor, pixels: torch.Tensor, confidence: torch.Tensor,
                 camera: VirtualCamera, times=None) -> torch.Tensor:
    """(T, 3) root translations (metres, camera frame) that best reproject points.

    relative: (T, K, 3) body points relative to the root, camera frame, metres; pixels (T, K, 2)
    and confidence (T, K) their detections. For a translation r, a point projects to
    u = fx (X + rx) / (Z + rz) + cx, i.e. fx rx - (u - cx) rz = (u - cx) Z - fx X (and likewise
    for v): linear in r.

    Without times: solved per frame by confidence-weighted least squares. Depth is the weak
    direction of that solve (it rests on the person's 2D size alone): a far person's root
    jumps by tens of centimetres between frames, and planted feet slide with it.
    With times ((T,) seconds, strictly increasing; 3 frames or more, else per frame): one linear
    solve for the whole track, the equations above scaled to metres at the person (divided by the
    focal length times the per-frame depth) over KEYPOINT_NOISE, plus the root's acceleration (second differences on
    the timestamps, m/s^2) over ROOT_ACCELERATION. Frames without keypoints are bridged by the
    acceleration term (a sparse banded system, scipy).
    """
    a, b = _root_equations(relative, pixels, camera)                                    # (T, 2K, 3), (T, 2K)
    w = torch.cat([confidence, confidence], 1).clamp_min(0).double()                     # (T, 2K)
    sqrt_w = w[..., None].sqrt()
    per_frame = torch.linalg.lstsq(a * sqrt_w, b[..., None] * sqrt_w).solution[..., 0]     # (T, 3)
    if times is None or len(relative) < 3 or not (np.diff(np.asarray(times, dtype=float)) > 0).all():
        return per_frame.to(relative.dtype)
    depth = (per_frame[:, 2:] + relative[..., 2].double().mean(1, keepdim=True)).clamp_min(0.5)   # (T, 1)
    focal = torch.cat([torch.full(pixels.shape[1:2], float(camera.fx)), torch.full(pixels.shape[1:2], float(camera.fy))])
    w = w / (focal.double() * depth * KEYPOINT_NOISE) ** 2
    normal = torch.einsum("tk,tki,tkj->tij", w, a, a).numpy()                          # (T, 3, 3)
    rhs = torch.einsum("tk,tki,tk->ti", w, a, b).numpy().reshape(-1)
    accel = second_differences(np.asarray(times, dtype=float)) / ROOT_ACCELERATION    # (T-2, T) per s^2
    system = scipy.sparse.block_diag(list(normal)) + scipy.sparse.kron(accel.T @ accel, scipy.sparse.identity(3))
    solution = scipy.sparse.linalg.spsolve(system.tocsc(), rhs)
    return torch.as_tensor(solution.reshape(-1, 3), dtype=relative.dtype)


def _root_equations(relative: torch.Tensor, pixels: torch.Tensor, camera: VirtualCamera):
    """(a (T, 2K, 3), b (T, 2K)) float64: a r = b on each frame (initial_root's docstring)."""
    fx, fy, cx, cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    u, v = pixels[..., 0] - cx, pixels[..., 1] - cy
    x, y, z = relative.unbind(-1)
    zeros = torch.zeros_like(u)
    rows_u = torch.stack([torch.full_like(u, fx), zeros, -u], -1)                       # (T, K, 3)
    rows_v = torch.stack([zeros, torch.full_like(v, fy), -v], -1)
    a = torch.cat([rows_u, rows_v], 1)                                                   # (T, 2K, 3)
    b = torch.cat([u * z - fx * x, v * z - fy * y], 1)                                   # (T, 2K)
    return a.double(), b.double()


def second_differences(times: np.ndarray) -> scipy.sparse.csr_matrix:
    """(T-2, T) sparse: row t maps values at times (T,) seconds to their second derivative at
    times[t+1] (per s^2), on unequal steps: 2 / (h0 + h1) * ((x2 - x1) / h1 - (x1 - x0) / h0)."""
    h = np.diff(times)
    h0, h1 = h[:-1], h[1:]
    scale = 2.0 / (h0 + h1)
    rows = np.repeat(np.arange(len(h0)), 3)
    cols = (np.arange(len(h0))[:, None] + np.arange(3)).reshape(-1)
    values = np.stack([scale / h0, -scale * (1 / h0 + 1 / h1), scale / h1], 1).reshape(-1)
    return scipy.sparse.csr_matrix((values, (rows, cols)), shape=(len(h0), len(times)))


def refine_capture(rotvecs: torch.Tensor, root: torch.Tensor, skeleton: Skeleton, camera: VirtualCamera,
                   pixels: torch.Tensor, confidence: torch.Tensor, network_joints: torch.Tensor,
                   prior: PosePrior, config: CaptureRefineConfig = CaptureRefineConfig(),
                   floor: tuple[torch.Tensor, float] | None = None, planted: torch.Tensor | None = None,
                   still: torch.Tensor | None = None):
    """Refined (rotvecs (T, 22, 3), root (T, 3)) of one person (module docstring).

    rotvecs, root: the starting pose (camera frame). skeleton: the person's template.
    camera: intrinsics (its extrinsics are ignored: everything is in the camera frame).
    pixels (T, 21, 2), confidence (T, 21): the person's detections in KEYPOINTS layout.
    network_joints: (T, 22, 3) the network's bone-corrected joints relative to the pelvis, metres.
    floor: (up (3,), camera height) of the floor in the camera frame, or None (no foot terms);
    planted: (T, 4) bool, the sole keypoints (SOLES order) planted on the floor on each frame;
    still: (T, 4) bool, soles that stay put without being known to touch the floor (E_skate only).
    """
    frames = len(root)
    confidence = torch.nan_to_num(confidence.float()).clamp(0, 1).double()
    pixels = torch.nan_to_num(pixels.float()).double()
    feet = floor is not None and bool(config.floor or config.skate or config.support)
    up, height = (floor[0].double(), float(floor[1])) if feet else (torch.zeros(3, dtype=torch.float64), 0.0)
    planted = torch.zeros(frames, len(SOLES), dtype=torch.bool) if planted is None or not feet else planted
    held = planted if still is None else planted | still
    terms = Terms(skeleton, camera, pixels, confidence, person_size(pixels, confidence), network_joints.double(), prior,
                  replace(config, init=config.init if frames > 1 else config.photo_init,
                          temporal=config.temporal if frames > 1 else 0.0),
                  up, height, feet, planted.double(), (held[1:] & held[:-1]).double())
    theta = rotvecs.detach().double().clone()
    r = root.detach().double().clone()
    iterations = config.iterations if frames > 1 else config.photo_iterations
    if config.compiled:
        minimise_lbfgs_with_gradient([theta, r], terms.compiled(theta, r), iterations)
    else:
        theta.requires_grad_(True)
        r.requires_grad_(True)
        minimise_lbfgs([theta, r], lambda: terms.energy(theta, r), iterations)
    return theta.detach().float(), r.detach().float()


@dataclass
class Terms:
    """What the refinement's energy (module docstring) is made of, for one person over T frames:
    the fixed inputs of :func:`refine_capture` in float64 (pixels (T, 21, 2), confidence (T, 21),
    size (T,) pixels: person_size, network (T, 22, 3) metres, up (3,) and height metres: the
    floor, feet: whether the foot terms are on, planted (T, 4) and held (T - 1, 4) 0/1), and
    the weights (config, E_init's and E_temporal's already set for the number of frames)."""

    skeleton: Skeleton
    camera: VirtualCamera
    pixels: torch.Tensor
    confidence: torch.Tensor
    size: torch.Tensor
    network: torch.Tensor
    prior: PosePrior
    config: CaptureRefineConfig
    up: torch.Tensor
    height: float
    feet: bool
    planted: torch.Tensor
    held: torch.Tensor

    def energy(self, theta: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """The energy at rotation vectors theta (T, 22, 3) and root r (T, 3), float64, written
        in torch (differentiable by autograd): the definition that the compiled code
        (:meth:`compiled`, several times faster) is tested against."""
        config = self.config
        world_r, joints = forward_kinematics_by_level(rot.convert(theta, "rotvec", "matrix"), torch.zeros_like(r),
                                                      self.skeleton.offsets.double(), self.skeleton.parents)
        points = body_keypoints_3d(world_r, joints, self.skeleton, keypoint_anchors(self.skeleton)) + r[:, None]
        projected, _ = intrinsics(self.camera).project(points)
        squared = (((projected - self.pixels) / self.size[:, None, None]) ** 2).sum(-1)
        if config.robust:
            squared = 2 * config.robust**2 * ((1 + squared / config.robust**2).sqrt() - 1)
        total = config.key * (self.confidence * squared).sum() + config.init * ((joints - self.network) ** 2).sum()
        total = total + config.prior * self.prior.energy(theta).sum()
        total = total + config.temporal * ((joints + r[:, None]).diff(dim=0) ** 2).sum()
        if self.feet:
            soles = points[:, SOLES]
            above = soles @ self.up + self.height                                           # (T, 4) metres
            total = total + config.floor * ((self.planted * above**2).sum() + (above.clamp_max(0) ** 2).sum())
            total = total + config.support * ((above.amin(1) - SUPPORT_TOLERANCE).clamp_min(0) ** 2).sum()
            total = total + config.skate * (self.held * (soles.diff(dim=0) ** 2).sum(-1)).sum()
        return total

    def compiled(self, theta: torch.Tensor, r: torch.Tensor):
        """A function that returns (the energy, [its gradient in theta (T, 22, 3), in r (T, 3)])
        at theta's and r's current values (float64 tensors), computed by
        humotion.capture.refine_energy; the gradient tensors are reused between calls."""
        from humotion.capture.refine_energy import refinement_energy   # here: it compiles (numba) on first use

        def array(values, dtype=np.float64) -> np.ndarray:
            return np.ascontiguousarray(torch.as_tensor(values).numpy(), dtype=dtype)

        config, precision = self.config, self.prior.precision.double()
        anchor_joints, anchor_offsets = keypoint_anchors(self.skeleton)
        _, rest = forward_kinematics_by_level(torch.eye(3, dtype=torch.float64).expand(len(self.skeleton.parents), 3, 3),
                                              torch.zeros(3, dtype=torch.float64), self.skeleton.offsets.double(),
                                              self.skeleton.parents)
        fixed = dict(
            parents=array(self.skeleton.parents, np.int64), rest=array(rest[None]),
            anchor_joints=array(anchor_joints, np.int64), anchor_offsets=array(anchor_offsets),
            camera=array([float(v) for v in (self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy)]),
            pixels=array(self.pixels), confidence=array(self.confidence), size=array(self.size),
            network=array(self.network), prior_mean=array(self.prior.mean),
            prior_precision=array((precision + precision.T) / 2),
            weights=array([config.key, config.init, config.prior, config.temporal, config.floor, config.skate,
                           config.support, config.robust]),
            up=array(self.up), height=self.height, feet=self.feet, soles=array(SOLES, np.int64),
            planted=array(self.planted), held=array(self.held), support_tolerance=SUPPORT_TOLERANCE)
        gradients = [torch.zeros_like(theta), torch.zeros_like(r)]

        def evaluate() -> tuple[float, list[torch.Tensor]]:
            value = refinement_energy(theta.detach().numpy(), r.detach().numpy(), theta_gradient=gradients[0].numpy(),
                                      root_gradient=gradients[1].numpy(), **fixed)
            return value, gradients

        return evaluate


def person_size(pixels: torch.Tensor, confidence: torch.Tensor, min_confidence: float = 0.3) -> torch.Tensor:
    """(T,) the person's 2D size in pixels per frame: the diagonal of the box around the confident
    keypoints (at least 1 pixel). pixels (T, K, 2), confidence (T, K)."""
    sure = (confidence >= min_confidence)[..., None]
    big = torch.finfo(pixels.dtype).max
    low = torch.where(sure, pixels, big).amin(1)
    high = torch.where(sure, pixels, -big).amax(1)
    diagonal = (high - low).norm(dim=-1)
    return torch.where(sure.any(1)[:, 0], diagonal, torch.ones_like(diagonal)).clamp_min(1.0)
