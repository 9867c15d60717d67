"""Fitting the body model's pose to observations by optimisation, within the joint limits.

Poses are optimised in the unconstrained parameters of :class:`humotion.body.limits.JointLimits`
(rotation vectors = centre + half * tanh(free), so every iterate is inside the boxes) with
L-BFGS (strong-Wolfe line search, autodiff gradients), together with the root translation.

    free, translation, before, after = fit_pose_to_vertices(body, targets, rest, free, translation)
    fit = fit_to_points(body, joints, names)                        # 3D joints (B, K, 3), metres
    fit = fit_to_points(body, pixels, names, camera=Camera.facing(3.0))   # 2D keypoints (B, K, 2)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from humotion.body.model import BodyModel


def vertex_distance_mm(vertices: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """(B, V, 3), (B, V, 3) -> (B,) mean per-vertex distance in millimetres."""
    return ((vertices - targets).norm(dim=-1) * 1000.0).mean(-1)


def fit_pose_to_vertices(body: BodyModel, targets: torch.Tensor, rest_vertices: torch.Tensor, free: torch.Tensor,
                         translation: torch.Tensor, expression: torch.Tensor | None = None, iterations: int = 20,
                         correctives: bool = True):
    """Pose bodies with known rest meshes onto target meshes (registrations).

    targets, rest_vertices (B, V, 3); free (B, J, 3) starting pose parameters (limits.to_free of
    rotation vectors); translation (B, 3); expression (B, expression_latent) or None. Minimises
    the sum over meshes of the mean vertex distance. Returns (free, translation, error before,
    error after (B,) mm), keeping each mesh's starting pose where the fit did not improve it.
    The model's own parameters get no gradients."""
    flags = [p.requires_grad for p in body.parameters()]
    body.requires_grad_(False)
    try:
        rest_vertices, targets = rest_vertices.detach(), targets.detach()
        expression = None if expression is None else expression.detach()

        def errors(f, t):
            out = body(expression=expression, pose=body.limits.to_matrix(f), translation=t,
                       rest_vertices=rest_vertices, correctives=correctives)
            return vertex_distance_mm(out.vertices, targets)

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
    finally:
        for p, flag in zip(body.parameters(), flags):
            p.requires_grad_(flag)


@dataclass
class Camera:
    """A pinhole camera, OpenCV axes (x right, y down, z forward): pixel = (f x / z + cx, f y / z + cy)
    of x = rotation @ world + translation. rotation (3, 3) world -> camera; translation (3,)."""

    focal: float
    principal: tuple[float, float]
    rotation: torch.Tensor
    translation: torch.Tensor

    @classmethod
    def facing(cls, distance: float = 3.0, height: float = 0.0, focal: float = 1000.0,
               principal: tuple[float, float] = (500.0, 500.0)) -> "Camera":
        """A camera `distance` m in front of the origin (on +Z, where the body faces), at `height`,
        looking at it along -Z."""
        rotation = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
        centre = torch.tensor([0.0, height, distance])
        return cls(focal, principal, rotation, -rotation @ centre)

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 2) pixels."""
        x = points @ self.rotation.T.to(points) + self.translation.to(points)
        z = x[..., 2:].clamp_min(1e-3)
        return self.focal * x[..., :2] / z + torch.tensor(self.principal, dtype=points.dtype, device=points.device)


@dataclass
class Fit:
    """A fit's result: shape (B, shape_latent), pose (B, J, 3) rotation vectors inside the joint
    limits, translation (B, 3), the posed output, and the final loss per item (B,)."""

    shape: torch.Tensor
    pose: torch.Tensor
    translation: torch.Tensor
    output: object
    loss: torch.Tensor


def initial_translation(camera: Camera, pixels: torch.Tensor, joints: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(B, 3) root translations that put joints (B, K, 3) (a starting pose at the origin) where
    their pixels (B, K, 2) are: the depth from the ratio of the joints' vertical extent to the
    pixels' (the body upright), the rest from the pixels' weighted centre."""
    seen = weights > 0
    big = torch.finfo(pixels.dtype).max
    extent_px = (torch.where(seen, pixels[..., 1], -big).amax(1) - torch.where(seen, pixels[..., 1], big).amin(1))
    extent_m = (torch.where(seen, joints[..., 1], -big).amax(1) - torch.where(seen, joints[..., 1], big).amin(1))
    depth = camera.focal * extent_m / extent_px.clamp_min(1.0)
    w = weights[..., None] / weights.sum(1, keepdim=True).clamp_min(1e-6)[..., None]
    centre_px = (w * pixels).sum(1)
    principal = torch.tensor(camera.principal, dtype=pixels.dtype)
    centre_camera = torch.cat([(centre_px - principal) * depth[:, None] / camera.focal, depth[:, None]], dim=-1)
    centre_world = (centre_camera - camera.translation.to(pixels)) @ camera.rotation.to(pixels)  # R^T (x - t)
    return centre_world - (w * joints).sum(1)


def fit_to_points(body: BodyModel, targets: torch.Tensor, joint_names, *, camera: Camera | None = None,
                  weights: torch.Tensor | None = None, fit_shape: bool = True, shape_prior: float = 1.0,
                  pose_prior: float = 10.0, iterations: int = 100, starts: tuple[float, ...] = (0.0,),
                  shape: torch.Tensor | None = None) -> Fit:
    """Fit pose, root translation and (fit_shape) the shape latent to observed joints.

    targets (B, K, 3) world joint positions (m), or (B, K, 2) pixels of `camera`; joint_names: the
    K rig joints they observe; weights (B, K) confidences (None: ones). Loss: the weighted mean
    squared distance (mm^2 in 3D, px^2 in 2D) plus shape_prior * the squared Mahalanobis distance
    of the shape latent under the training subjects' latent Gaussian (its start) plus pose_prior * the squared rotation angles of the joints below the root (keeps the
    rig's unobserved joints near rest). The pose stays inside the joint limits (L-BFGS on the
    limits' free parameters); in 3D the root rotation and translation are fitted alone first (a
    quarter of the iterations); in 2D the start is placed by the keypoints' size and centre
    (:func:`initial_translation`). starts: initial root yaws (radians) tried one after another,
    the best fit kept (several initial poses, for the front/back ambiguity of a single view)."""
    names = list(body.joint_names)
    missing = [n for n in joint_names if n not in names]
    if missing:
        raise ValueError(f"joint_names has joints the rig lacks: {missing}")
    index = torch.tensor([names.index(n) for n in joint_names])
    targets = body._tensor("targets", targets)
    dims = 2 if camera is not None else 3
    if targets.dim() != 3 or targets.shape[1:] != (len(index), dims):
        raise ValueError(f"targets must be (B, {len(index)}, {dims}), got {tuple(targets.shape)}")
    batch = len(targets)
    weights = torch.ones(batch, len(index)) if weights is None else body._tensor("weights", weights).reshape(batch, -1)
    scale = 1000.0 if camera is None else 1.0
    flags = [p.requires_grad for p in body.parameters()]
    body.requires_grad_(False)
    best: Fit | None = None
    try:
        for yaw in starts:
            z = body.shape_latent_mean.expand(batch, -1).clone() if shape is None else shape.detach().clone()
            z.requires_grad_(fit_shape)
            rotvec = torch.zeros(batch, body.num_joints, 3)
            rotvec[:, 0, 1] = yaw
            free = body.limits.to_free(rotvec).requires_grad_(True)
            with torch.no_grad():
                rest = body(shape=z, pose=body.limits.to_rotvec(free)).joints[:, index]
                shift = (initial_translation(camera, targets, rest, weights) if camera is not None else
                         ((targets - rest) * weights[..., None]).sum(1) / weights.sum(1, keepdim=True).clamp_min(1e-6))
            translation = shift.clone().requires_grad_(True)
            root = torch.zeros(body.num_joints, 1)
            root[0] = 1.0
            start = free.detach().clone()

            def losses(stage: int = 1):
                rotvec = body.limits.to_rotvec(free if stage else start + (free - start) * root)
                out = body(shape=z, pose=rotvec, translation=translation)
                joints = out.joints[:, index]
                predicted = joints if camera is None else camera.project(joints)
                residual = ((predicted - targets) * scale).square().sum(-1)
                data = (weights * residual).sum(1) / weights.sum(1).clamp_min(1e-6)
                prior = shape_prior * body.shape_prior(z) + pose_prior * rotvec[:, 1:].square().sum((-1, -2))
                return data + prior, out

            stages = [(1, [free, translation] + ([z] if fit_shape else []), iterations)]
            if camera is None:  # in 3D, place and turn the body first (in 2D that drifts in depth)
                stages.insert(0, (0, [free, translation], max(iterations // 4, 1)))
            for stage, variables, steps in stages:
                optimizer = torch.optim.LBFGS(variables, lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")

                def closure():
                    optimizer.zero_grad()
                    loss = losses(stage)[0].sum()
                    loss.backward()
                    return loss

                with torch.enable_grad():
                    optimizer.step(closure)
                if stage == 0:
                    with torch.no_grad():
                        free.copy_(start + (free - start) * root)
            with torch.no_grad():
                loss, out = losses()
            fit = Fit(z.detach(), body.limits.to_rotvec(free).detach(), translation.detach(), out, loss)
            if best is None:
                best = fit
            else:
                better = fit.loss < best.loss
                best = Fit(torch.where(better[:, None], fit.shape, best.shape),
                           torch.where(better[:, None, None], fit.pose, best.pose),
                           torch.where(better[:, None], fit.translation, best.translation), None,
                           torch.minimum(fit.loss, best.loss))
        if best.output is None:
            with torch.no_grad():
                best.output = body(shape=best.shape, pose=best.pose, translation=best.translation)
        return best
    finally:
        for p, flag in zip(body.parameters(), flags):
            p.requires_grad_(flag)
