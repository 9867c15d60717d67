"""The learned body model at run time: parameters -> vertices, joints and faces.

    from humotion.body.model import load_body_model
    body = load_body_model("low")                          # or "full", or a weights file
    shape = body.shape_from_measurements(height=[1.80], weight=[75.0])   # (1, 16) latent
    out = body(shape=shape, pose=rotations, translation=None, expression=None)
    out.vertices (B, V, 3), out.joints (B, J, 3), body.faces (faces, 3)

X = M(pose, shape, expression): the shape VAE's decoder gives the rest mesh (A pose, neutral
face) from a shape latent; the joint regressor its joint centres; the expression VAE's decoder
rest-pose facial offsets from an expression latent (zero latent: neutral); the pose correctives
offsets from the pose; linear blend skinning with the learned weights poses the sum:

    rest = template + decode_shape(shape)                            (B, V, 3)
    rest_joints = joint_regressor(rest)                              (B, J, 3)
    vertices = LBS(rest + decode_expression(expression) + correctives(pose), weights, pose, rest_joints)

The forward pass forms that sum block by block of vertices and skins each block while it is in
cache: on the CPU without gradients (inference) vertex-major, with the batch last, in a compiled
loop (:mod:`humotion.body.cpu_posing`, numba); otherwise, differentiably, in torch
(:mod:`humotion.body.torch_posing`). The tests hold the two equal. What inference derives from
the weights (dense skinning weights, float16 copies, ...) is kept between calls
(:mod:`humotion.body.derived`).

Poses follow :mod:`humotion.body.skinning` (per-joint rest-relative rotations in world-aligned
rest axes, root translation from the rest position), on the 76-joint rig `body.joint_names`, as
rotation matrices (B, J, 3, 3), wxyz quaternions (B, J, 4) or rotation vectors (B, J, 3). The
model is torch float32 (and numba for CPU inference): batched, differentiable in every input, no
network and no Anny at run time. Metres, Y up, the body faces +Z, the pelvis near the origin at rest.

Inputs are checked (:mod:`humotion.body.checks`): wrong shapes, NaN / infinite values and
measurements outside the range the model was trained on (height, weight, BMI:
:mod:`humotion.body.anthropometry`) raise ValueError naming the parameter. Weight files are
:mod:`humotion.model_files` files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from humotion import rotations as rot
from humotion.body import anthropometry, cpu_posing, torch_posing
from humotion.body.anthropometry import mesh_height
from humotion.body.checks import batch_size, checked, checked_tensor
from humotion.body.correctives import PoseCorrectives
from humotion.body.cpu_posing import bone_transforms, rows_product, vertex_major_heights
from humotion.body.derived import DerivedTensors
from humotion.body.joints import JointRegressor
from humotion.body.limits import JointLimits
from humotion.body.skinning import LearnedSkinWeights, SkinBlocks, needs_gradient, skinning_transforms
from humotion.body.torch_posing import planar
from humotion.body.vae import VAE
from humotion.model_files import load_model_file, save_model_file

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "body"
REGIONS = ("body", "face", "hands")


@dataclass
class BodyConfig:
    """Sizes of a body model (all its tensors follow from these).

    resolution: a name ("full", "low"). num_vertices, num_faces, joint_names, parents: the mesh
    and the rig. shape_*: the shape VAE (latent size, MLP width, width of the decoder's last
    hidden layer = the span of its linear output layer, vertices its encoder reads).
    expression_*: the same for the expression VAE, which moves `expression_vertices` vertices.
    corrective_hidden: width of the pose correctives' shared ReLU layer (correctives=False: none).
    skin_support: bones per vertex that may carry skinning weight. joint_support: vertices per
    joint in the joint regressor; joint_bound: soft bound of a joint-centre correction (m).
    """

    resolution: str = "low"
    num_vertices: int = 0
    num_faces: int = 0
    joint_names: tuple[str, ...] = ()
    parents: tuple[int, ...] = ()
    shape_latent: int = 16
    """Shape latent size (the spec's 16 or 64)."""
    shape_hidden: int = 256
    shape_basis: int = 64
    shape_points: int = 0
    expression_latent: int = 20
    """Expression latent size."""
    expression_hidden: int = 128
    expression_basis: int = 64
    expression_vertices: int = 0
    expression_points: int = 0
    corrective_hidden: int = 32
    correctives: bool = True
    """Pose correctives (--no-correctives: an ablation)."""
    skin_support: int = 12
    joint_support: int = 64
    joint_bound: float = 0.05
    measurement_features: int = 4

    def __post_init__(self):
        self.joint_names = tuple(self.joint_names)
        self.parents = tuple(int(p) for p in self.parents)


@dataclass
class BodyOutput:
    """What the body model gives for a batch of B parameter sets.

    vertices (B, V, 3) posed mesh; joints (B, J, 3) posed joint centres; rest_vertices (B, V, 3)
    the rest (A-pose) mesh with expression and correctives left out; rest_joints (B, J, 3);
    world_rotations (B, J, 3, 3) and translations (B, J, 3) of the bones' skinning transforms
    (x -> A x + t), for exporting a skinned mesh. vertices and rest_vertices are (B, V, 3) views
    of the layout the forward pass computes in: vertex-major (V, 3, B) on the CPU without
    gradients, coordinate planes (B, 3, V) otherwise. Index and reshape them freely, or call
    .contiguous() before .view()."""

    vertices: torch.Tensor
    joints: torch.Tensor
    rest_vertices: torch.Tensor
    rest_joints: torch.Tensor
    world_rotations: torch.Tensor
    translations: torch.Tensor


def wide_addmm(offset: torch.Tensor, factors: torch.Tensor, rows: torch.Tensor, piece: int = 2 ** 18) -> torch.Tensor:
    """offset (N,) or (B, N) + factors (B, K) @ rows (N, K).T -> (B, N); a result of over 4 pieces'
    size (B N numbers) is computed in column blocks of about `piece` numbers each, which torch's
    MKL runs faster for the shape decoder's mesh-wide product (N = 3 V, K = 64) at large batches
    (the body model card's Speed section; bench/body_products.py). Without a gradient to keep,
    each block is written straight into the result (with one, they are joined at the end)."""
    if len(factors) * len(rows) <= 4 * piece:
        return torch.addmm(offset, factors, rows.T)
    columns = max(piece // len(factors), 1)
    pieces = zip(offset.split(columns, -1), rows.split(columns))
    if needs_gradient(offset, factors, rows):
        return torch.cat([torch.addmm(o, factors, r.T) for o, r in pieces], -1)
    out = factors.new_empty(len(factors), len(rows))
    for (o, r), target in zip(pieces, out.split(columns, -1)):
        torch.addmm(o, factors, r.T, out=target)
    return out


class BodyModel(nn.Module):
    """The body model; see the module docstring. Build one with :func:`load_body_model` (or
    :func:`humotion.body.train.initial_model` for training)."""

    def __init__(self, config: BodyConfig):
        super().__init__()
        self.config = c = config
        V, J = c.num_vertices, len(c.joint_names)
        self.register_buffer("template", torch.zeros(V, 3))
        self.register_buffer("faces", torch.zeros(c.num_faces, 3, dtype=torch.long))
        for region in REGIONS:
            self.register_buffer(f"region_{region}", torch.zeros(V, dtype=torch.bool))
        self.register_buffer("shape_points", torch.zeros(c.shape_points, dtype=torch.long))
        self.register_buffer("shape_scale", torch.ones(()))
        self.register_buffer("expression_index", torch.zeros(c.expression_vertices, dtype=torch.long))
        self.register_buffer("expression_points", torch.zeros(c.expression_points, dtype=torch.long))
        self.register_buffer("expression_scale", torch.ones(()))
        self.register_buffer("template_height", torch.ones(()))
        self.register_buffer("volume_scale", torch.ones(()))
        # anthropometric controls: ranges seen in training and a regressor to the shape latent
        self.register_buffer("height_range", torch.tensor([0.0, math.inf]))
        self.register_buffer("weight_range", torch.tensor([0.0, math.inf]))
        self.register_buffer("bmi_range", torch.tensor([0.0, math.inf]))
        self.register_buffer("measurement_stats", torch.tensor([[0.0, 1.0], [0.0, 1.0]]))
        self.register_buffer("measurement_regressor", torch.zeros(c.measurement_features, c.shape_latent))
        # the latents' distribution over the training data (Gaussians fitted to the encoder means)
        self.register_buffer("shape_latent_mean", torch.zeros(c.shape_latent))
        self.register_buffer("shape_latent_cholesky", torch.eye(c.shape_latent))
        self.register_buffer("expression_latent_mean", torch.zeros(c.expression_latent))
        self.register_buffer("expression_latent_cholesky", torch.eye(c.expression_latent))
        self.shape_vae = VAE(3 * c.shape_points, 3 * V, c.shape_latent, c.shape_hidden, c.shape_basis)
        self.expression_vae = VAE(3 * c.expression_points, 3 * c.expression_vertices, c.expression_latent,
                                  c.expression_hidden, c.expression_basis)
        self.joint_regressor = JointRegressor(V, J, c.joint_support, c.joint_bound)
        self.correctives = PoseCorrectives(V, c.joint_names, c.parents, c.corrective_hidden) if c.correctives else None
        self.skin = LearnedSkinWeights(V, J, c.skin_support)
        self.limits = JointLimits(J)
        self.derived = DerivedTensors()
        # the compiled CPU path's kinematics take the parents as an array, each before its children
        self._parent_indices = torch.tensor(c.parents, dtype=torch.int32)
        self._parents_first = all(p < j for j, p in enumerate(c.parents))
        self._keep_parameter_tuples()

    def _keep_parameter_tuples(self) -> None:
        """Keep the parameters that every call looks at in tuples (cheaper than walking the
        modules on every call). Optimisers, .to() and load_state_dict update parameters in place;
        a load_state_dict(assign=True), which replaces them, takes new tuples."""
        self._all_parameters = tuple(self.parameters())
        self._expression_parameters = tuple(self.expression_vae.parameters())
        self._joint_parameters = tuple(self.joint_regressor.parameters())

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """nn.Module.load_state_dict, then the parameter tuples taken again."""
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._keep_parameter_tuples()
        return result

    # -- properties ---------------------------------------------------------------------------
    @property
    def joint_names(self) -> list[str]:
        return list(self.config.joint_names)

    @property
    def parents(self) -> list[int]:
        return list(self.config.parents)

    @property
    def num_vertices(self) -> int:
        return self.config.num_vertices

    @property
    def num_joints(self) -> int:
        return len(self.config.joint_names)

    def region(self, name: str) -> torch.Tensor:
        """(V,) bool mask of a region: body, face or hands."""
        if name not in REGIONS:
            raise ValueError(f"region must be one of {REGIONS}, got {name!r}")
        return getattr(self, f"region_{name}")

    def skinning_weights(self) -> torch.Tensor:
        """(V, J) learned skinning weights (rows sum to 1)."""
        return self.derived.get("skin", [self.skin.logits], self.skin)

    def skin_blocks(self) -> SkinBlocks:
        """The skinning weights in the blocked form linear_blend_skinning multiplies by (kept
        between calls at inference, like the weights)."""
        return self.derived.get("skin_blocks", [self.skin.logits], lambda: SkinBlocks(self.skinning_weights()))

    # -- the components -----------------------------------------------------------------------
    def encode_shape(self, rest_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest meshes (B, V, 3) (A pose, neutral face, this model's topology and frame) ->
        mean, log variance (B, shape_latent) of the shape latent."""
        rest_vertices = checked("rest_vertices", rest_vertices, (self.num_vertices, 3), self.template)
        x = (rest_vertices[:, self.shape_points] - self.template[self.shape_points]) / self.shape_scale
        return self.shape_vae.encode(x.flatten(1))

    def decode_shape(self, shape: torch.Tensor) -> torch.Tensor:
        """Shape latents (B, shape_latent) -> rest meshes (B, V, 3), a view of coordinate planes
        (B, 3, V) (see :func:`humotion.body.torch_posing.planar`): template + shape_scale x the decoder's output."""
        return self.decode_shape_and_joints(shape)[0]

    def decode_shape_and_joints(self, shape: torch.Tensor,
                                vertex_major: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape latents (B, shape_latent) -> rest meshes (B, V, 3) (as decode_shape) and their
        joint centres (B, J, 3) (as rest_joints), both linear in the decoder's last hidden layer
        h (B, basis) up to the joints' bounded corrections: the meshes are one product of h with
        the output weights (rows as planes), the joints' centre and correction sums one product
        with those weights already summed over each joint's support (J x 6 rows, not 3 V).
        vertex_major=True: the meshes are a (B, V, 3) view of (V, 3, B) instead (the layout of
        :mod:`humotion.body.cpu_posing`)."""
        vae, output, V = self.shape_vae, self.shape_vae.output, self.num_vertices
        scale = self.shape_scale

        def products():
            rest_at_zero = self.template + scale * output.bias.unflatten(0, (V, 3))           # (V, 3)
            rows = torch.cat([output.weight.unflatten(0, (V, 3)), rest_at_zero[..., None]], -1)
            sums = self.joint_regressor.linear_sums(rows).flatten(0, 2)                          # (2 J 3, basis + 1)
            return (planar(output.weight), planar(rest_at_zero.flatten()), rest_at_zero.flatten(), sums[:, :-1],
                    sums[:, -1])

        tensors = [output.weight, output.bias, self.template, scale, *self._joint_parameters]
        mesh_weight, mesh_offset, offset_rows, joint_weight, joint_offset = self.derived.get(
            "shape_products", tensors, products)
        h = vae.decoder(shape) * scale
        if vertex_major:
            half = self.derived.float16_bits("shape", output.weight, len(h))
            rest = rows_product(offset_rows[:, None], output.weight, half, h)
            rest = rest.view(V, 3, -1).permute(2, 0, 1)
        else:
            rest = wide_addmm(mesh_offset, h, mesh_weight).unflatten(-1, (3, V)).transpose(1, 2)
        centre, correction = torch.addmm(joint_offset, h, joint_weight.T).unflatten(-1, (2, -1, 3)).unbind(1)
        return rest, self.joint_regressor.bounded(centre, correction)

    def encode_expression(self, offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest-pose expression offsets (B, V, 3) (expressive minus neutral rest mesh) -> mean, log
        variance (B, expression_latent)."""
        offsets = checked("expression offsets", offsets, (self.num_vertices, 3), self.template)
        x = offsets[:, self.expression_index[self.expression_points]] / self.expression_scale
        return self.expression_vae.encode(x.flatten(1))

    def decode_expression(self, expression: torch.Tensor) -> torch.Tensor:
        """Expression latents (B, expression_latent) -> rest-pose offsets (B, V, 3), exactly zero
        for the zero latent and away from the face."""
        moved = self.expression_moves(expression)
        out = torch.zeros(len(expression), self.num_vertices, 3, dtype=moved.dtype, device=moved.device)
        return out.index_copy(1, self.expression_index, moved)

    def expression_moves(self, expression: torch.Tensor, vertex_major: bool = False) -> torch.Tensor:
        """Expression latents (B, expression_latent) -> offsets (B, expression_vertices, 3) of the
        vertices the expressions move (`expression_index`; the rest of decode_expression is zeros).
        vertex_major=True: a view of (expression_vertices, 3, B) (see decode_shape_and_joints)."""
        vae = self.expression_vae
        neutral = self.derived.get("neutral", self._expression_parameters,
                                   lambda: vae.decoder(torch.zeros_like(expression[:1])))      # h(0), (1, basis)
        # decode(z) - decode(0) = W (h(z) - h(0)), h the last hidden layer: no bias to add
        hidden = (vae.decoder(expression) - neutral) * self.expression_scale                  # (B, basis)
        if not vertex_major:
            return (hidden @ vae.output.weight.T).unflatten(-1, (-1, 3))
        half = self.derived.float16_bits("expression", vae.output.weight, len(hidden))
        moves = rows_product(None, vae.output.weight, half, hidden)
        return moves.view(-1, 3, len(expression)).permute(2, 0, 1)

    def rest_joints(self, rest_vertices: torch.Tensor) -> torch.Tensor:
        """Joint centres (B, J, 3) of rest meshes (B, V, 3)."""
        return self.joint_regressor(rest_vertices)

    def corrective_offsets(self, rotations: torch.Tensor, rest_vertices: torch.Tensor) -> torch.Tensor:
        """Pose-corrective offsets (B, V, 3) of rotation matrices (B, J, 3, 3) on bodies with
        rest meshes (B, V, 3) (their height scales the offsets); zero without correctives."""
        if self.correctives is None:
            return torch.zeros_like(rest_vertices)
        return self.correctives(rotations, self.corrective_scale(rest_vertices))

    def corrective_scale(self, rest_vertices: torch.Tensor, vertex_major: bool = False) -> torch.Tensor:
        """(B,) factor of the pose correctives for bodies with rest meshes (B, V, 3): their height
        over the template's (the correctives are learned at template size). vertex_major=True:
        measured by the compiled path's kernel, for views of (V, 3, B) meshes, without gradients."""
        heights = vertex_major_heights(rest_vertices) if vertex_major else mesh_height(rest_vertices)
        return heights / self.template_height

    # -- the forward pass ---------------------------------------------------------------------
    def forward(self, shape=None, expression=None, pose=None, translation=None, *,
                correctives: bool = True, rest_vertices=None) -> BodyOutput:
        """Posed bodies of a batch of parameters (see the module docstring).

        shape (B, shape_latent) latent (None: zeros, the mean body); expression
        (B, expression_latent) latent (None: neutral); pose (B, J, 3, 3) / (B, J, 4) wxyz /
        (B, J, 3) rotation vectors (None: the rest pose); translation (B, 3) of the root from its
        rest position (None: zero). rest_vertices (B, V, 3): pose this rest mesh instead of
        decoding `shape`. correctives=False leaves the pose correctives out. Single (unbatched)
        parameter sets are accepted too; batch-1 inputs broadcast against the others.
        """
        c = self.config
        like = self.template
        shape = None if shape is None else checked("shape", shape, (c.shape_latent,), like)
        expression = None if expression is None else checked("expression", expression, (c.expression_latent,), like)
        rotations = None if pose is None else self.pose_matrices(pose)
        translation = None if translation is None else checked("translation", translation, (3,), like)
        if rest_vertices is not None:
            if shape is not None:
                raise ValueError("give shape or rest_vertices, not both (rest_vertices replace the decoded shape)")
            rest_vertices = checked("rest_vertices", rest_vertices, (c.num_vertices, 3), like)
        batch = batch_size(shape=shape, expression=expression, pose=rotations, translation=translation,
                           rest_vertices=rest_vertices)
        device = self.template.device
        compiled = self._poses_compiled(shape, expression, rotations, translation, rest_vertices)
        if rest_vertices is None:
            if shape is None:
                shape = torch.zeros(1, c.shape_latent, device=device)
            rest_vertices, rest_joints = self.decode_shape_and_joints(shape, vertex_major=compiled)
        else:
            rest_joints = self.rest_joints(rest_vertices)
            if compiled:   # laid out once as the compiled path reads it (heights, posing)
                rest_vertices = rest_vertices.permute(1, 2, 0).contiguous().permute(2, 0, 1)
        if rotations is None:
            rotations = torch.eye(3, device=device).expand(batch, self.num_joints, 3, 3)
        rotations = rotations.expand(batch, -1, -1, -1)
        translation = torch.zeros(batch, 3, device=device) if translation is None else translation.expand(batch, 3)
        factors = moves = None
        if correctives and self.correctives is not None and pose is not None:
            scale = self.corrective_scale(rest_vertices, vertex_major=compiled).expand(batch)
            factors = self.correctives.factors(rotations, scale)
        if expression is not None:
            moves = self.expression_moves(expression, vertex_major=compiled)    # (B or 1, E, 3)
        if compiled:
            A, t, joints = bone_transforms(rest_joints, self._parent_indices, rotations, translation)
            vertices = cpu_posing.pose_body(self, rest_vertices, factors, moves, A, t)
        else:
            A, t, joints = skinning_transforms(rest_joints.expand(batch, -1, -1), self.parents, rotations, translation)
            vertices = torch_posing.pose_in_blocks(self, rest_vertices.expand(batch, -1, -1), factors, moves, A, t)
        return BodyOutput(vertices, joints, rest_vertices.expand(batch, -1, -1), rest_joints.expand(batch, -1, -1), A, t)

    def _poses_compiled(self, *inputs: torch.Tensor | None) -> bool:
        """Whether the forward pass of these inputs takes :mod:`humotion.body.cpu_posing`'s
        compiled path: on the CPU, in float32, with no gradient to keep (and a rig listing every
        parent before its children, as the shipped ones do)."""
        if self.template.device.type != "cpu" or self.template.dtype != torch.float32:
            return False
        if torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in (*inputs, *self._all_parameters)):
            return False
        return self._parents_first

    def pose_matrices(self, pose) -> torch.Tensor:
        """A pose in any accepted form -> (B, J, 3, 3) float32 rotation matrices (quaternions are
        normalised; matrices are used as given)."""
        J = self.num_joints
        pose = checked_tensor("pose", pose, self.template)
        if pose.shape[-2:] == (3, 3) and pose.dim() >= 3 and pose.shape[-3] == J:
            out = pose
        elif pose.dim() >= 2 and pose.shape[-2] == J and pose.shape[-1] == 4:
            norm = pose.norm(dim=-1, keepdim=True)
            if (norm < 1e-6).any():
                raise ValueError("pose has zero-length quaternions")
            out = rot.quat_to_matrix(pose / norm)
        elif pose.dim() >= 2 and pose.shape[-2] == J and pose.shape[-1] == 3:
            out = rot.convert(pose, "rotvec", "matrix")
        else:
            raise ValueError(f"pose must be (B, {J}, 3, 3) rotation matrices, (B, {J}, 4) wxyz quaternions or "
                             f"(B, {J}, 3) rotation vectors on the rig's {J} joints, got {tuple(pose.shape)}")
        if out.dim() == 3:
            out = out[None]
        if out.dim() != 4:
            raise ValueError(f"pose must have one batch dimension, got {tuple(pose.shape)}")
        return out

    def pose_from_canonical(self, canonical_rotations, shape=None) -> torch.Tensor:
        """Rig poses (B, J, 3, 3) from poses of humotion's 22-joint canonical body (B, 22, 4)
        wxyz or (B, 22, 3, 3) local rotations (a canonical Motion's rotations), retargeted onto
        this body's rig (:func:`humotion.body.posing.canonical_to_rig`; fingers and eyes at
        rest). shape (1, shape_latent) or None (the mean body). Not differentiable."""
        from humotion.body.posing import canonical_to_rig

        rotations = checked_tensor("canonical_rotations", canonical_rotations, self.template)
        if rotations.dim() == 2 or rotations.dim() == 3 and rotations.shape[-2:] == (3, 3):
            rotations = rotations[None]
        if rotations.dim() < 3 or rotations.shape[1] != 22 or rotations.shape[2:] not in ((4,), (3, 3)):
            raise ValueError(f"canonical_rotations must be (B, 22, 4) or (B, 22, 3, 3), got {tuple(rotations.shape)}")
        with torch.no_grad():
            shape = torch.zeros(1, self.config.shape_latent) if shape is None else checked(
                "shape", shape, (self.config.shape_latent,), self.template)
            if len(shape) != 1:
                raise ValueError(f"shape must be one body's latent (1, {self.config.shape_latent}), got {tuple(shape.shape)}")
            rest, joints = self.decode_shape_and_joints(shape.to(self.template))
        local = canonical_to_rig(rotations.double().cpu(), rest[0].double().cpu(), joints[0].double().cpu(),
                                 self.joint_names, self.parents)
        return local.to(self.template)

    # -- anthropometry (humotion.body.anthropometry) ------------------------------------------
    def measure(self, rest_vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        """Height (m), weight (kg) and BMI, (B,) each, of rest meshes (B, V, 3), as Anny measures
        them (weight calibrated to the full-resolution mesh's volume):
        :func:`humotion.body.anthropometry.measure`."""
        return anthropometry.measure(rest_vertices, self.faces, self.volume_scale)

    def shape_from_measurements(self, height, weight, iterations: int = 30, prior: float = 0.01) -> torch.Tensor:
        """Shape latents (B, shape_latent) of bodies with the given heights (m) and weights (kg),
        each (B,) or a number; ValueError outside the trained range:
        :func:`humotion.body.anthropometry.shape_from_measurements`."""
        return anthropometry.shape_from_measurements(self, height, weight, iterations, prior)

    # -- latent spaces ------------------------------------------------------------------------
    def sample_shapes(self, count: int, generator: torch.Generator | None = None, temperature: float = 1.0,
                      prior: bool = False) -> torch.Tensor:
        """(B, shape_latent) random body shapes, B = count: draws from the Gaussian fitted to the training
        subjects' latent means (mean + temperature * L eps), or with prior=True from the VAE's
        N(0, temperature^2 I). The first is the one that looks like the data: with a KL weight
        small enough for millimetre reconstructions the latent is not spread like its prior (a
        few directions, height and girth among them, are several times wider)."""
        eps = temperature * torch.randn(count, self.config.shape_latent, generator=generator).to(self.template.device)
        return eps if prior else self.shape_latent_mean + eps @ self.shape_latent_cholesky.T

    def sample_expressions(self, count: int, generator: torch.Generator | None = None, temperature: float = 1.0,
                           prior: bool = False) -> torch.Tensor:
        """(B, expression_latent) random expressions, B = count, like :meth:`sample_shapes` (the fitted
        Gaussian of random facial-action mixes, or the N(0, I) prior)."""
        eps = temperature * torch.randn(count, self.config.expression_latent, generator=generator).to(self.template.device)
        return eps if prior else self.expression_latent_mean + eps @ self.expression_latent_cholesky.T


def interpolate(a: torch.Tensor, b: torch.Tensor, steps: int, spherical: bool = False) -> torch.Tensor:
    """(steps, D) latents from a to b (both (D,) or (1, D)), ends included: linear, or spherical
    (slerp, which keeps the norm typical of the Gaussian prior between two samples)."""
    a, b = a.reshape(-1), b.reshape(-1)
    t = torch.linspace(0.0, 1.0, steps, dtype=a.dtype, device=a.device)[:, None]
    if not spherical:
        return (1 - t) * a + t * b
    cos = torch.dot(a, b) / (a.norm() * b.norm()).clamp_min(1e-12)
    omega = torch.arccos(cos.clamp(-1.0, 1.0))
    if omega < 1e-6:
        return (1 - t) * a + t * b
    return (torch.sin((1 - t) * omega) * a + torch.sin(t * omega) * b) / torch.sin(omega)


# -- files ------------------------------------------------------------------------------------------

def save_body_model(model: BodyModel, path: str | Path, half: bool = False, **extra) -> None:
    """Write a weights file (humotion.model_files format). half: store the big weight matrices
    (over 100k numbers) as float16, halving the file; they load back as float32."""
    save_model_file(model, path, half_over=100_000 if half else None, **extra)


def shipped_weights(resolution: str) -> Path:
    """Path of the weights shipped for a resolution ("low" or "full")."""
    return ASSETS / f"body_{resolution}.pt"


LATENT_STATISTICS = frozenset({"shape_latent_mean", "shape_latent_cholesky", "expression_latent_mean",
                               "expression_latent_cholesky"})
"""Buffers a weights file may lack: without them the model samples from the N(0, I) prior."""


def load_body_model(source: str | Path = "low", map_location="cpu") -> BodyModel:
    """A BodyModel in eval mode, without gradients, from a shipped resolution name ("low",
    "full"), a weights file of :func:`save_body_model` or a training checkpoint (the
    BodyTrainer's, its body model's config under "model", its tensors under "body.") by
    :func:`humotion.model_files.load_model_file`. FileNotFoundError where there is no file;
    ValueError naming the file and the problem for a damaged file or another network's."""
    path = shipped_weights(str(source)) if str(source) in ("low", "full") else Path(source)
    if not path.exists():
        raise FileNotFoundError(f"no body model weights at {path}: train them with `humotion train body` "
                                f"or give a weights file")
    model = load_model_file(path, BodyModel, BodyConfig, map_location, inside=("model", "body"),
                            optional=LATENT_STATISTICS)
    model.requires_grad_(False)
    return model
