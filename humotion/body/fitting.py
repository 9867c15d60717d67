"""Fitting the body model to observations by optimisation, inside its joint limits.

    fit = fit_to_joints(body, joints, names)                       # 3D points (B, K, 3), metres
    fit = fit_to_keypoints(body, keypoints, confidences, camera)   # detector keypoints (B, 21, 2), pixels
    fit = fit_shape_to_keypoint_frames(body, keypoints, confidences, camera)   # (T, 21, 2): one shape, T poses
    fit.shape, fit.pose, fit.translation, fit.vertices, fit.joints, fit.height
    free, translation, before, after = fit_pose_to_vertices(body, meshes, rest, free, translation)

Points. A fit observes named points of the body: rig joints (``body.joint_names``) or the 2D
detector keypoints of video capture (:data:`humotion.capture.detection.KEYPOINTS`). The
shoulder, elbow, wrist, hip, knee and ankle keypoints are the rig joints that capture's canonical
joints of those names drive (:data:`humotion.body.posing.CANONICAL_TO_RIG`), the eyes the eyeball
joints; the nose, ears, heels and big toes are mesh vertices picked on the model's mean rest mesh
(:func:`keypoint_vertices`).

Objective, per body (twice the negative log-posterior under the assumptions below):

    sum_k c_k |p_k - y_k|^2 / sigma_k^2  +  |w|^2  +  sum_(joints j below the root) |theta_j|^2 / pose_sigma^2

p_k the body's point k (in 2D its projection), y_k its observation, c_k its confidence (0: the
point is ignored), sigma_k its noise per axis (3D: `noise` metres; 2D: the detector noise model
of :mod:`humotion.capture.keypoints`, `noise` x KEYPOINT_SIGMAS[k] x the square root of the
keypoints' box area); w the shape latent whitened under the training subjects' Gaussian
(z = mean + L w, so |w|^2 is the shape prior; left out when the shape is given); theta_j joint
j's rotation vector (zero: the rig's A pose), a weak pull for what the points leave open
(twists, the spine's inner bones).

Optimisation, one body at a time (a batch's shared line search would slow every body down):
L-BFGS (strong-Wolfe line search, autodiff gradients) on w, the root translation, the root
rotation (a rotation vector composed onto a start orientation, unbounded) and the other joints'
rotations in the unconstrained parameters of :class:`humotion.body.limits.JointLimits` (rotation
vector = centre + half * tanh(free)), so every iterate is inside the joint limits. Starts, the
body at rest with the mean shape (or the given one): in 3D the root rotation and translation
that best align its points (Kabsch); in 2D upright, facing the camera and facing away (one view's
front/back ambiguity), at the depth where its size matches the keypoints'. The starts' root
rotations and translations are refined first (a fifth of `iterations`), the best start kept,
then everything optimised (`iterations`). The pose correctives are left out while fitting (they
move the surface by millimetres) and put back in the result.
"""

from __future__ import annotations

import functools
import math
import weakref
from dataclasses import dataclass, fields

import roma
import torch

from humotion import rotations as rot
from humotion.body.anthropometry import mesh_height
from humotion.body.checks import checked, checked_tensor
from humotion.body.model import BodyModel
from humotion.body.posing import CANONICAL_TO_RIG
from humotion.body.skinning import linear_blend_skinning, skinning_transforms
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import KEYPOINT_SIGMAS, VirtualCamera

KEYPOINT_JOINTS = {**{name: CANONICAL_TO_RIG[name] for name in KEYPOINTS if name in CANONICAL_TO_RIG},
                   "left_eye": "eye.L", "right_eye": "eye.R"}
"""Detector keypoint -> the rig joint it is."""

# -- points on the body -------------------------------------------------------------------------

_VERTICES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def keypoint_vertices(body: BodyModel) -> dict[str, int]:
    """Detector keypoint -> mesh vertex index, for the keypoints that are not rig joints; picked
    on the mean rest mesh (A pose, facing +Z, Y up, the person's left at +X) among the vertices
    each bone skins most: the nose the head's most forward vertex; an ear the head's outermost
    vertex on its side within 6 cm below the eyes; a heel its foot's rearmost vertex; a big toe
    its foot's most forward vertex, leaning to the midline (forward + half the inward distance).
    Cached per model."""
    if body not in _VERTICES:
        with torch.no_grad():
            rest = body.decode_shape(body.shape_latent_mean[None])[0]
            eye_level = body.rest_joints(rest[None])[0, body.joint_names.index("eye.L"), 1]
        bone = body.skinning_weights().argmax(1)

        def skinned_by(*names):
            return torch.isin(bone, torch.tensor([body.joint_names.index(n) for n in names])).nonzero()[:, 0]

        def most(vertices, score):
            return int(vertices[score(rest[vertices]).argmax()])

        head = skinned_by("head", "eye.L", "eye.R")
        picks = {"nose": most(head, lambda v: v[:, 2])}
        for side, s, sign in (("left", "L", 1.0), ("right", "R", -1.0)):
            level = head[(rest[head, 1] < eye_level) & (rest[head, 1] > eye_level - 0.06)]
            foot = skinned_by(f"foot.{s}")
            picks[f"{side}_ear"] = most(level, lambda v: sign * v[:, 0])
            picks[f"{side}_heel"] = most(foot, lambda v: -v[:, 2])
            picks[f"{side}_big_toe"] = most(foot, lambda v: v[:, 2] - 0.5 * sign * v[:, 0])
        _VERTICES[body] = picks
    return _VERTICES[body]


def point_index(body: BodyModel, names) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where named points (rig joints or detector keypoints) are on the body, as (K,) tensors: is
    a joint (bool), the joint's index, the vertex's index (0 where unused). ValueError for a name
    that is neither."""
    joints, vertices = [], []
    vertex_of = keypoint_vertices(body)
    for name in names:
        joint = KEYPOINT_JOINTS.get(name, name)
        if joint not in body.joint_names and name not in vertex_of:
            raise ValueError(f"unknown point {name!r}: names must be rig joints (body.joint_names) or "
                             f"detector keypoints (humotion.capture.detection.KEYPOINTS)")
        joints.append(body.joint_names.index(joint) if joint in body.joint_names else -1)
        vertices.append(vertex_of.get(name, -1))
    joints, vertices = torch.tensor(joints), torch.tensor(vertices)
    return joints >= 0, joints.clamp_min(0), vertices.clamp_min(0)


def body_points(body: BodyModel, joints: torch.Tensor, vertices: torch.Tensor, names) -> torch.Tensor:
    """(B, K, 3) positions (m) of named points (rig joints or detector keypoints) on posed bodies
    with joints (B, J, 3) and vertices (B, V, 3), e.g. a BodyOutput's."""
    is_joint, joint, vertex = point_index(body, names)
    return torch.where(is_joint[:, None], joints[:, joint], vertices[:, vertex])


def _posed_points(body: BodyModel, rest: torch.Tensor, rotations: torch.Tensor, translation: torch.Tensor,
                  index: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """(N, K, 3) points (point_index's `index`) of posed bodies: BodyModel's forward pass without
    correctives and expression, skinning only the points' vertices (the fit's inner loop).
    rest (N or 1, V, 3) decoded rest meshes, metres; rotations (N, J, 3, 3); translation (N, 3)."""
    is_joint, joint, vertex = index
    A, t, joints = skinning_transforms(body.rest_joints(rest), body.parents, rotations, translation)
    vertices = linear_blend_skinning(rest[:, vertex], body.skinning_weights()[vertex], A, t)
    return torch.where(is_joint[:, None], joints[:, joint], vertices)


# -- fitting ------------------------------------------------------------------------------------

@dataclass
class Fit:
    """A fit's result for B bodies.

    shape (B, shape_latent) latent; pose (B, J, 3) rotation vectors (the root's its global
    orientation), every joint inside the limits; translation (B, 3) of the root from its rest
    position, metres; vertices (B, V, 3) and joints (B, J, 3) of the fitted posed bodies, metres
    (with the pose correctives); points (B, K, 3) their observed points, metres; height (B,) the
    fitted body's standing height (its rest mesh's, as :meth:`BodyModel.measure` gives it),
    metres; loss (B,) the objective of the module docstring at the fit (as optimised: without
    the correctives)."""

    shape: torch.Tensor
    pose: torch.Tensor
    translation: torch.Tensor
    vertices: torch.Tensor
    joints: torch.Tensor
    points: torch.Tensor
    height: torch.Tensor
    loss: torch.Tensor


def fit_to_joints(body: BodyModel, joints, names, confidences=None, *, shape=None, noise: float = 0.02,
                  pose_sigma: float = 3.0, iterations: int = 100) -> Fit:
    """Fit a body (shape, pose, root translation) to 3D points.

    joints (B, K, 3) or (K, 3): world positions, metres (Y up), of the points `names` (K rig
    joint names or detector keypoint names; see the module docstring). confidences (B, K) or
    (K,) in [0, 1] (None: ones); a point of confidence 0 is ignored (its position may be NaN).
    shape (B or 1, shape_latent): keep this shape (e.g. ``body.shape_from_measurements``) instead
    of fitting one. noise: the points' standard deviation per axis, metres. pose_sigma: radians
    of the pose prior. iterations: L-BFGS iterations. Needs 3 or more points per body.
    """
    _positive(noise=noise, pose_sigma=pose_sigma)
    targets, confidences = _observations(body, joints, confidences, len(names), 3)
    sigma = torch.full(confidences.shape, float(noise))
    return _fit(body, targets, confidences, sigma, names, None, shape, pose_sigma, iterations)


def fit_to_keypoints(body: BodyModel, keypoints, confidences, camera: VirtualCamera, *, shape=None,
                     noise: float = 1.0, pose_sigma: float = 3.0, iterations: int = 100) -> Fit:
    """Fit a body (shape, pose, root translation) to 2D detector keypoints seen by a camera.

    keypoints (B, 21, 2) or (21, 2): pixels in the detector layout
    :data:`~humotion.capture.detection.KEYPOINTS`; confidences (B, 21) or (21,) in [0, 1], 0 for
    a missing keypoint (its pixels may be anything, NaN included). camera: a VirtualCamera of
    batch shape () (one for all) or (B,), world Y up. shape (B or 1, shape_latent): keep this
    shape instead of fitting one. noise: the keypoints' error relative to the detector noise
    model's (module docstring; 1: about a good COCO detector's; lower for cleaner keypoints, which
    then weigh more against the priors). pose_sigma: radians of the pose prior. iterations:
    L-BFGS iterations. Needs 3 or more keypoints per body.

    One view fixes the body's proportions, not its size: a body k times larger k times farther
    away looks the same (up to perspective), so a fitted shape's size (fit.height) comes from its
    proportions and the shape prior; give `shape` where the height is known.
    """
    _positive(noise=noise, pose_sigma=pose_sigma)
    targets, confidences = _observations(body, keypoints, confidences, len(KEYPOINTS), 2)
    low, high = _box(targets, confidences)
    scale = (high - low).prod(-1).sqrt()[:, None]
    sigma = noise * torch.tensor(KEYPOINT_SIGMAS) * scale
    return _fit(body, targets, confidences, sigma, KEYPOINTS, camera, shape, pose_sigma, iterations)


def fit_shape_to_keypoint_frames(body: BodyModel, keypoints, confidences, camera: VirtualCamera, *,
                                 noise: float = 1.0, pose_sigma: float = 3.0, warm_iterations: int = 60,
                                 iterations: int = 100) -> Fit:
    """Fit ONE body shape, shared by all frames, and a pose and root translation per frame, to the
    2D detector keypoints of T frames of one person seen by one fixed camera (a video).

    keypoints (T, 21, 2) pixels and confidences (T, 21) as in :func:`fit_to_keypoints`; camera a
    VirtualCamera of batch shape (). Frames with fewer than 3 keypoints of confidence above 0 are
    left out (ValueError if none is left). The objective is the sum over frames of
    fit_to_keypoints' data and pose-prior terms plus one shape prior |w|^2. Optimisation: each
    frame first fitted alone with the mean shape (fit_to_keypoints, `warm_iterations`), then the
    shared shape latent and every frame's root rotation, joint rotations (inside the limits) and
    translation optimised together (L-BFGS, `iterations`). Returns a Fit of the T' kept frames
    (shape and height the same in every row). One camera still leaves the size open (module
    docstring of fit_to_keypoints): the height comes from the proportions that many poses pin
    down, through the shape space. With detector-like keypoints that height is no better than a
    fixed 1.65 m (bench/height_from_image.py --frames 12), so capture does not use it.
    """
    _positive(noise=noise, pose_sigma=pose_sigma)
    if camera.fx.dim() > 0:
        raise ValueError("camera must have batch shape () (one fixed camera for all frames)")
    keypoints = torch.as_tensor(keypoints, dtype=torch.float32)
    confidences = checked_tensor("confidences", confidences, body.template)
    if keypoints.dim() != 3 or confidences.shape != keypoints.shape[:2]:
        raise ValueError(f"keypoints must be (T, {len(KEYPOINTS)}, 2) and confidences (T, {len(KEYPOINTS)}), got "
                         f"{tuple(keypoints.shape)} and {tuple(confidences.shape)}")
    kept = (confidences > 0).sum(1) >= 3
    if not kept.any():
        raise ValueError("a fit needs a frame with 3 or more keypoints of confidence above 0")
    targets, confidences = _observations(body, keypoints[kept], confidences[kept], len(KEYPOINTS), 2)
    low, high = _box(targets, confidences)
    sigma = noise * torch.tensor(KEYPOINT_SIGMAS) * (high - low).prod(-1).sqrt()[:, None]
    mean, cholesky = body.shape_latent_mean, body.shape_latent_cholesky
    frames = len(targets)
    index = point_index(body, KEYPOINTS)
    with _frozen(body):
        warm = [_fit_one(body, targets[i:i + 1], confidences[i:i + 1], sigma[i:i + 1], index, camera, mean[None],
                         pose_sigma, warm_iterations) for i in range(frames)]
        _, pose, translation, _ = (torch.cat(x) for x in zip(*warm))
        orientation = rot.convert(pose[:, 0], "rotvec", "matrix")
        turn = torch.zeros(frames, 3)
        free = body.limits.to_free(pose, eps=1e-2)
        w = torch.zeros(1, body.config.shape_latent)
        # the roots' world positions as if the body kept the mean's size: a body k times larger k
        # times farther from the camera looks the same, so each root is placed at the camera centre
        # + k (position - centre), k the shape's height over the mean's; changing the size then
        # moves every frame along with it (L-BFGS crawls along that valley otherwise)
        mean_rest = body.decode_shape(mean[None])
        mean_height, mean_root = mesh_height(mean_rest), body.rest_joints(mean_rest)[:, 0]
        centre = camera.position
        position = mean_root + translation

        def parameters():
            """z (T, shape_latent), rotations (T, J, 3, 3), rotation vectors (T, J, 3), translations (T, 3)."""
            rotvec = body.limits.to_rotvec(free)
            root = orientation @ rot.convert(turn, "rotvec", "matrix")
            rotations = torch.cat([root[:, None], rot.convert(rotvec[:, 1:], "rotvec", "matrix")], dim=1)
            z = mean + w @ cholesky.T
            rest, rest_joints = body.decode_shape_and_joints(z)
            size = mesh_height(rest) / mean_height
            shift = centre + size[:, None] * (position - centre) - rest_joints[:, 0]
            return z, rest, rotations, rotvec, shift

        def objective():
            """(T,) each frame's data and pose terms, and the shape prior."""
            _, rest, rotations, rotvec, shift = parameters()
            predicted = camera.project(_posed_points(body, rest, rotations, shift, index))[0]
            data = (confidences * (predicted - targets).square().sum(-1) / sigma.square()).sum(-1)
            return data + rotvec[:, 1:].square().sum((-1, -2)) / pose_sigma**2, w.square().sum()

        variables = [w, turn, free, position]
        for v in variables:
            v.requires_grad_(True)
        optimizer = torch.optim.LBFGS(variables, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure():
            optimizer.zero_grad()
            frame_terms, shape_prior = objective()
            loss = frame_terms.sum() + shape_prior
            loss.backward()
            return loss

        with torch.enable_grad():
            optimizer.step(closure)
        with torch.no_grad():
            z, _, rotations, rotvec, shift = parameters()
            z = z.expand(frames, -1)
            rotvec[:, 0] = rot.convert(rotations[:, 0], "matrix", "rotvec")
            frame_terms, shape_prior = objective()
            out = body(shape=z, pose=rotvec, translation=shift)
            points = body_points(body, out.joints, out.vertices, KEYPOINTS)
            return Fit(z.clone(), rotvec, shift.detach().clone(), out.vertices, out.joints, points,
                       mesh_height(out.rest_vertices), frame_terms + shape_prior / frames)


def _positive(**values: float) -> None:
    """ValueError naming any of the values (noise, pose_sigma, ...) that is no positive number."""
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value}")


def _observations(body: BodyModel, points, confidences, count: int, dims: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations as (B, K, dims) float tensors, missing ones (confidence 0) zeroed, and
    confidences (B, K); ValueError for wrong shapes, NaN where confidence > 0, or < 3 points."""
    points = torch.as_tensor(points, dtype=torch.float32)
    points = points[None] if points.dim() == 2 else points
    if points.dim() != 3 or points.shape[1:] != (count, dims):
        raise ValueError(f"the points must be (B, {count}, {dims}) or ({count}, {dims}), got {tuple(points.shape)}")
    confidences = (torch.ones(points.shape[:2]) if confidences is None
                   else checked_tensor("confidences", confidences, body.template))
    if tuple(confidences.shape) not in ((count,), (len(points), count)):
        raise ValueError(f"confidences must be ({len(points)}, {count}) or ({count},), got {tuple(confidences.shape)}")
    confidences = confidences.expand(len(points), count)
    if ((confidences < 0) | (confidences > 1)).any():
        raise ValueError("confidences must be in [0, 1]")
    seen = confidences > 0
    if not torch.isfinite(points[seen]).all():
        raise ValueError("the points contain NaN or infinite values where their confidence is above 0")
    if (seen.sum(1) < 3).any():
        raise ValueError("a fit needs 3 or more points with confidence above 0 per body")
    return torch.where(seen[..., None], points, 0.0), confidences


def _fit(body: BodyModel, targets: torch.Tensor, confidences: torch.Tensor, sigma: torch.Tensor, names,
         camera: VirtualCamera | None, shape, pose_sigma: float, iterations: int) -> Fit:
    """The fit of the module docstring, body by body. targets (B, K, 3 or 2), confidences and
    sigma (B, K); shape (B or 1, shape_latent) or None; camera of batch shape () or (B,), or None."""
    batch = len(targets)
    if shape is not None:
        shape = checked("shape", shape, (body.config.shape_latent,), body.template)
        if len(shape) not in (1, batch):
            raise ValueError(f"shape must have batch size 1 or {batch}, got {len(shape)}")
        shape = shape.expand(batch, -1)
    cameras = [camera] * batch
    if camera is not None and camera.fx.dim() > 0:
        if camera.fx.shape != (batch,):
            raise ValueError(f"camera must have batch shape () or ({batch},), got {tuple(camera.fx.shape)}")
        cameras = [VirtualCamera(*(getattr(camera, f.name)[i] for f in fields(camera))) for i in range(batch)]
    index = point_index(body, names)
    with _frozen(body):
        fits = [_fit_one(body, targets[i:i + 1], confidences[i:i + 1], sigma[i:i + 1], index, cameras[i],
                         None if shape is None else shape[i:i + 1], pose_sigma, iterations) for i in range(batch)]
        with torch.no_grad():
            z, pose, translation, loss = (torch.cat(x) for x in zip(*fits))
            out = body(shape=z, pose=pose, translation=translation)
            points = body_points(body, out.joints, out.vertices, names)
            return Fit(z, pose, translation, out.vertices, out.joints, points, mesh_height(out.rest_vertices), loss)


def _fit_one(body: BodyModel, targets: torch.Tensor, confidences: torch.Tensor, sigma: torch.Tensor, index,
             camera: VirtualCamera | None, shape: torch.Tensor | None, pose_sigma: float, iterations: int):
    """One body's fit (module docstring), batch 1 in and out: shape (1, shape_latent), pose (1, J, 3)
    rotation vectors, translation (1, 3), loss (1,)."""
    fit_shape = shape is None
    mean, cholesky = body.shape_latent_mean, body.shape_latent_cholesky
    with torch.no_grad():
        z = mean[None] if fit_shape else shape
        start_rest = body.decode_shape(z)        # also the rest mesh throughout when the shape is given
        root = body.rest_joints(start_rest)[:, 0]
        rest_points = _posed_points(body, start_rest, torch.eye(3).expand(1, body.num_joints, 3, 3), torch.zeros(1, 3), index)
        place = _align if camera is None else functools.partial(_face_camera, camera=camera)
        orientation, translation = place(rest_points, root, targets, confidences)
        # the shape as whitened coordinates under the training subjects' Gaussian: z = mean + L w,
        # the prior |w|^2 (L-BFGS converges several times faster than on z)
        w = torch.linalg.solve_triangular(cholesky, (z - mean)[..., None], upper=False)[..., 0]
    starts = len(orientation)
    w = w.expand(starts, -1).clone()
    turn = torch.zeros(starts, 3)                            # root rotation vector after `orientation`
    free = body.limits.to_free(torch.zeros(starts, body.num_joints, 3))
    shift = translation.clone()

    def parameters():
        """z (S, shape_latent), rotations (S, J, 3, 3) and rotation vectors (S, J, 3) (the root's unused)."""
        rotvec = body.limits.to_rotvec(free)
        root = orientation @ rot.convert(turn, "rotvec", "matrix")
        rotations = torch.cat([root[:, None], rot.convert(rotvec[:, 1:], "rotvec", "matrix")], dim=1)
        return mean + w @ cholesky.T, rotations, rotvec

    def objective():
        """(S,) the loss of each start."""
        z, rotations, rotvec = parameters()
        points = _posed_points(body, body.decode_shape(z) if fit_shape else start_rest, rotations, shift, index)
        predicted = points if camera is None else camera.project(points)[0]
        data = (confidences * (predicted - targets).square().sum(-1) / sigma.square()).sum(-1)
        prior = rotvec[:, 1:].square().sum((-1, -2)) / pose_sigma**2
        return data + prior + (w.square().sum(-1) if fit_shape else 0.0)

    def minimise(variables, steps):
        for v in variables:
            v.requires_grad_(True)
        optimizer = torch.optim.LBFGS(variables, lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")

        def closure():
            optimizer.zero_grad()
            loss = objective().sum()
            loss.backward()
            return loss

        with torch.enable_grad():
            optimizer.step(closure)

    minimise([turn, shift], max(iterations // 5, 1))
    with torch.no_grad():
        best = int(objective().argmin())
    orientation = orientation[best:best + 1]
    w, turn, free, shift = (x[best:best + 1].detach().clone() for x in (w, turn, free, shift))
    minimise([turn, free, shift] + ([w] if fit_shape else []), iterations)
    with torch.no_grad():
        z, rotations, rotvec = parameters()
        rotvec[:, 0] = rot.convert(rotations[:, 0], "matrix", "rotvec")
        return z, rotvec, shift.detach(), objective()


def _align(points: torch.Tensor, root: torch.Tensor, targets: torch.Tensor, confidences: torch.Tensor):
    """The start of a 3D fit: the root rotation (1, 3, 3) and translation (1, 3) that move a body
    whose points are `points` (1, K, 3) and root joint `root` (1, 3) onto `targets` (1, K, 3)
    (weighted least squares, rotating about the root)."""
    rotation, offset = roma.rigid_points_registration(points, targets, confidences)
    return rotation, offset + (rotation @ root[..., None])[..., 0] - root


def _face_camera(points: torch.Tensor, root: torch.Tensor, pixels: torch.Tensor, confidences: torch.Tensor,
                 camera: VirtualCamera):
    """The two starts of a 2D fit: root rotations (2, 3, 3) upright, facing the camera and facing
    away, and translations (2, 3) that put the points' centre on the keypoints' centre at the
    depth where the points' box diagonal matches the keypoints' (as if facing the camera).
    points (1, K, 3) of a body at rest with its root joint at `root` (1, 3); pixels (1, K, 2);
    camera of batch shape ()."""
    weights = (confidences / confidences.sum())[0, :, None]                                     # (K, 1)
    depth = camera.fx * _box_diagonal(points, confidences) / _box_diagonal(pixels, confidences)   # (1,)
    principal, focal = torch.stack([camera.cx, camera.cy]), torch.stack([camera.fx, camera.fy])
    in_camera = torch.cat([((weights * pixels[0]).sum(0) - principal) / focal * depth, depth])
    centre = camera.rotation.T @ (in_camera - camera.translation)                                 # world (3,)
    towards = camera.position - centre
    yaw = torch.atan2(towards[0], towards[2]) + torch.tensor([0.0, math.pi])                      # (2,)
    orientation = rot.convert(yaw[:, None] * torch.tensor([0.0, 1.0, 0.0]), "rotvec", "matrix")
    offset = (weights * points[0]).sum(0) - root[0]                    # the points' centre from the root
    return orientation, centre - root[0] - orientation @ offset


def _box(points: torch.Tensor, confidences: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, D) lowest and highest corners of the bounding box of the points (B, K, D) with
    confidence above 0."""
    seen = (confidences > 0)[..., None]
    big = torch.finfo(points.dtype).max
    return torch.where(seen, points, big).amin(1), torch.where(seen, points, -big).amax(1)


def _box_diagonal(points: torch.Tensor, confidences: torch.Tensor) -> torch.Tensor:
    """(B,) diagonal of the bounding box of the points (B, K, D) with confidence above 0."""
    low, high = _box(points, confidences)
    return (high - low).norm(dim=-1)


class _frozen:
    """Context: the model's own parameters get no gradients (their flags restored on exit)."""

    def __init__(self, body: BodyModel):
        self.body = body

    def __enter__(self):
        self.flags = [p.requires_grad for p in self.body.parameters()]
        self.body.requires_grad_(False)

    def __exit__(self, *exc):
        for p, flag in zip(self.body.parameters(), self.flags):
            p.requires_grad_(flag)


# -- registered meshes (training) ---------------------------------------------------------------

def _vertex_distance_mm(vertices: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """(B, V, 3), (B, V, 3) metres -> (B,) mean per-vertex distance in millimetres."""
    return ((vertices - targets).norm(dim=-1) * 1000.0).mean(-1)


def fit_pose_to_vertices(body: BodyModel, targets: torch.Tensor, rest_vertices: torch.Tensor, free: torch.Tensor,
                         translation: torch.Tensor, expression: torch.Tensor | None = None, iterations: int = 20,
                         correctives: bool = True):
    """Pose bodies with known rest meshes onto target meshes (registrations), within the limits.

    targets, rest_vertices (B, V, 3) metres; free (B, J, 3) starting pose in the limits'
    unconstrained parameters (``body.limits.to_free`` of rotation vectors); translation (B, 3)
    metres; expression (B, expression_latent) or None. Minimises (L-BFGS, `iterations`) the sum
    over meshes of the mean vertex distance. Returns (free (B, J, 3), translation (B, 3), error
    before, error after (B,) mm), keeping each mesh's starting pose where the fit did not improve
    it. The model's own parameters get no gradients."""
    with _frozen(body):
        rest_vertices, targets = rest_vertices.detach(), targets.detach()
        expression = None if expression is None else expression.detach()

        def errors(f, t):
            out = body(expression=expression, pose=body.limits.to_matrix(f), translation=t,
                       rest_vertices=rest_vertices, correctives=correctives)
            return _vertex_distance_mm(out.vertices, targets)

        with torch.no_grad():
            before = errors(free, translation)
        f = free.detach().clone().requires_grad_(True)
        t = translation.detach().clone().requires_grad_(True)
        optimizer = torch.optim.LBFGS([f, t], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure():
            optimizer.zero_grad()
            loss = errors(f, t).sum()
            loss.backward()
            return loss

        with torch.enable_grad():
            optimizer.step(closure)
        with torch.no_grad():
            after = errors(f, t)
            better = after < before
            f = torch.where(better[:, None, None], f, free)
            t = torch.where(better[:, None], t, translation)
            after = torch.minimum(after, before)
        return f.detach(), t.detach(), before, after
