"""Training the body model end to end on registered meshes: ``humotion train body --help``.

    from humotion.body.train import BodyTrainConfig, train
    summary = train(BodyTrainConfig(data_root="runs/body_data", resolution="low", out_dir="runs/body/low"))

Data: a body data folder of :mod:`humotion.body.dataset` (``python -m humotion.body.dataset``):
the training split's posed meshes (held-out shapes and poses are never seen), their subjects'
neutral rest meshes and rest joint centres, their pose parameters and facial-action activations,
and Anny's skinning weights and expression basis (both only as starting points / data); and,
when the folder has them (:mod:`humotion.body.rest_shapes`), extra subjects' rest shapes and
joints for the shape-space terms (shape VAE, joint regressor, height/weight controls).

Initialisation (:func:`initial_model`): template = the mean training rest mesh; the VAEs' output
layers start from principal components (shape: of the training rest meshes; expression: of
random facial-action offsets), then both VAEs are warmed up alone on their reconstructions
(`warmup_steps`); the joint regressor's supports come from the skinning weights and its weights
are fitted (ridge regression) to the training rest joints; skinning weights start from Anny's; joint limits come
from the training poses (:mod:`humotion.body.limits`); correctives start at zero.

One loop, one shared loss (everything trained together): each step takes a batch of training
meshes and, through the whole model (shape VAE with a sampled latent -> joints -> expression
VAE -> correctives -> learned LBS), compares the posed mesh with the registration. Loss terms
(mean per-vertex distances in mm unless noted; weights in `weights`):

- posed: model mesh vs registered mesh; rest: decoded vs true rest mesh (the VAE's
  reconstruction), for the batch's subjects plus `shape_batch` extra ones; expression: decoded vs true expression offsets on the vertices expressions
  move, for the batch's meshes plus `synthetic_expressions` random facial-action mixes;
- joints: regressed vs true rest joint centres (the data has them; a scan pipeline would not);
- kl_shape, kl_expression: the VAEs' KL terms (nats per sample);
- bones: 1 - cos between predicted and template bone directions; sparsity: sum of square roots of
  the joint regressor's correction weights (L1); smooth: squared uniform-Laplacian of the correctives (mm^2);
  corrective: their squared size (mm^2).

Alternation: every `pose_every` epochs from `pose_start` on, each training mesh's pose (76 joint
rotations within the joint limits + root translation) is re-optimised with L-BFGS against the
current model (:func:`humotion.body.fitting.fit_pose_to_vertices`), starting from its current
value (at first the data's pose parameters) and kept only where it lowers that mesh's error; the
Adam steps in between update the model with the poses fixed.

Output folder and resume: as every training command (:mod:`humotion.training`): checkpoints (with
the per-mesh poses), log.jsonl, body.pt (final weights, :func:`humotion.body.model.load_body_model`)
and body_best.pt (lowest validation error: the meshes of `validation_subjects` training subjects
held out of training, given poses; the test splits are never used in training or selection).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from humotion import rotations as rot
from humotion.body import files
from humotion.body.anthropometry import DENSITY, measurement_features, mesh_height, mesh_volume
from humotion.body.evaluation import load_meshes, summarise, vertex_errors
from humotion.body.fitting import fit_pose_to_vertices
from humotion.body.joints import bone_direction_loss, farthest_points, joint_support
from humotion.body.model import BodyConfig, BodyModel, save_body_model
from humotion.body.vae import VAE, kl_divergence
from humotion.training import RunConfig, Session, fit, learning_rate

log = logging.getLogger("humotion.body.train")


def loss_weights(**overrides) -> dict[str, float]:
    """The loss terms' weights (see the module docstring), with overrides."""
    weights = dict(posed=1.0, rest=1.0, expression=1.0, joints=1.0, kl_shape=0.01, kl_expression=0.01,
                   bones=100.0, sparsity=0.02, smooth=0.1, corrective=0.001)
    unknown = set(overrides) - set(weights)
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}; terms: {sorted(weights)}")
    weights.update(overrides)
    return weights


@dataclass
class BodyTrainConfig(RunConfig):
    """Everything a body-model training run needs; saved in every checkpoint. The run settings
    (steps, seed, device, files) are humotion.training.RunConfig's; data_root is a body data
    folder. Also: resolution ("low" or "full"); lr_warmup (steps: a fresh Adam's first steps would
    shake the warmed-up VAEs), lr_final (cosine decay); pose_every, pose_start (epochs;
    pose_every 0: never re-optimise poses), pose_iterations (L-BFGS
    iterations), pose_batch (meshes per L-BFGS problem); synthetic_expressions and shape_batch
    (extra subjects' rest shapes for the shape-space terms) per step;
    warmup_steps of the VAEs before the end-to-end loop; validation_subjects: training subjects held out for validation; weights (loss terms); model: the body model's sizes."""

    data_root: str = "runs/body_data"
    """Body data folder (python -m humotion.body.command data)."""
    out_dir: str = "runs/body/low"
    resolution: str = "low"
    batch_size: int = 16
    lr: float = 3e-4
    lr_final: float = 2e-5
    """Learning rate at the end of the cosine decay from lr."""
    lr_warmup: int = 200
    epochs: int = 60
    """Epochs over the training meshes."""
    grad_clip: float = 10.0
    checkpoint_every: int = 200
    pose_every: int = 10
    """Epochs between pose re-optimisations (0: never)."""
    pose_start: int = 10
    """First epoch with a pose re-optimisation."""
    pose_iterations: int = 15
    """L-BFGS iterations per re-optimisation."""
    pose_batch: int = 64
    synthetic_expressions: int = 16
    shape_batch: int = 16
    warmup_steps: int = 2000
    """Steps warming the VAEs up alone first."""
    validation_subjects: int = 8
    weights: dict = field(default_factory=loss_weights)
    model: BodyConfig = field(default_factory=BodyConfig)

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = BodyConfig(**self.model)
        if self.resolution not in files.RESOLUTIONS:
            raise ValueError(f"resolution must be one of {files.RESOLUTIONS}, got {self.resolution!r}")
        if self.validation_subjects < 1:
            raise ValueError(f"validation_subjects must be at least 1 (the best checkpoint is chosen on their meshes), "
                             f"got {self.validation_subjects}")
        self.weights = loss_weights(**self.weights)


# -- data ------------------------------------------------------------------------------------------

class BodyData:
    """The training split of one resolution in memory (float32 tensors on `device`; without the
    meshes of its last `validation_subjects` subjects, `validation_shapes`), and the
    shape space's subjects (shape_rest (S, V, 3), shape_joints, shape_height, shape_mass): the
    training meshes' subjects plus the folder's extra rest shapes (:mod:`humotion.body.rest_shapes`)
    when it has them."""

    def __init__(self, folder, resolution: str, device="cpu", validation_subjects: int = 0):
        model = files.load_model_file(folder, resolution)
        split = files.load_split(folder, resolution, "train")
        subjects = np.unique(split["shape_id"])
        self.validation_shapes = subjects[len(subjects) - validation_subjects:] if validation_subjects else subjects[:0]
        kept = ~np.isin(split["shape_id"], self.validation_shapes)   # the validation subjects' meshes leave training
        split = {k: split[k][kept] for k in ("vertices", "shape_id", "rotations", "translation", "expression")}
        shapes = files.load_shapes(folder)
        t = lambda x: torch.as_tensor(np.asarray(x)).to(device)  # noqa: E731
        self.resolution = resolution
        self.faces = model["faces"].astype(np.int64)
        self.joint_names = [str(n) for n in model["joint_names"]]
        self.parents = [int(p) for p in model["parents"]]
        self.anny_weights = model["skin_weights"]
        self.regions = {r: model[f"region_{r}"] for r in ("body", "face", "hands")}
        self.vertices = t(split["vertices"])
        self.shape_id = t(split["shape_id"])
        self.rotvec = rot.convert(torch.as_tensor(split["rotations"]).double(), "quat", "rotvec").float().to(device)
        self.translation = t(split["translation"])
        self.expression = t(split["expression"])
        self.basis = t(model["expression_basis"])
        self.rest_vertices = t(model["rest_vertices"])
        self.rest_joints = t(model["rest_joints"])
        self.train_shapes = torch.unique(self.shape_id)
        self.height = t(shapes["height"])
        self.mass = t(shapes["mass"])
        # the shape space's subjects: the training meshes' plus the folder's extra rest shapes
        extra = files.load_rest_shapes(folder, resolution)
        self.extra_shapes = 0 if extra is None else len(extra["rest_vertices"])
        pool = [(self.rest_vertices[self.train_shapes], self.rest_joints[self.train_shapes],
                 self.height[self.train_shapes], self.mass[self.train_shapes])]
        if extra is not None:
            pool.append((t(extra["rest_vertices"]), t(extra["rest_joints"]), t(extra["height"]), t(extra["mass"])))
        self.shape_rest, self.shape_joints, self.shape_height, self.shape_mass = (torch.cat(x) for x in zip(*pool))

    def __len__(self) -> int:
        return len(self.vertices)

    def offsets(self, activations: torch.Tensor) -> torch.Tensor:
        """Facial-action activations (B, 52) -> rest-pose expression offsets (B, V, 3)."""
        return torch.einsum("be,evc->bvc", activations, self.basis)


def random_activations(count: int, actions: int, generator: torch.Generator, max_active: int = 4) -> torch.Tensor:
    """(B, actions) facial-action mixes, B = count, like the data's expressive meshes: 1..max_active
    actions per row at strengths uniform in [0.3, 1]."""
    active = torch.randint(1, max_active + 1, (count, 1), generator=generator)
    rank = torch.rand(count, actions, generator=generator).argsort(-1).argsort(-1)
    strength = 0.3 + 0.7 * torch.rand(count, actions, generator=generator)
    return strength * (rank < active)


def uniform_laplacian(faces: np.ndarray, num_vertices: int) -> torch.Tensor:
    """Sparse (V, V) L with (L x)_v = x_v - mean of v's mesh neighbours."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(np.concatenate([edges, edges[:, ::-1]]), axis=1), axis=0)
    edges = np.concatenate([edges, edges[:, ::-1]])
    degree = np.bincount(edges[:, 0], minlength=num_vertices).clip(min=1)
    rows = np.concatenate([np.arange(num_vertices), edges[:, 0]])
    cols = np.concatenate([np.arange(num_vertices), edges[:, 1]])
    values = np.concatenate([np.ones(num_vertices), -1.0 / degree[edges[:, 0]]])
    return torch.sparse_coo_tensor(np.stack([rows, cols]), values.astype(np.float32), (num_vertices,) * 2,
                                   check_invariants=True).coalesce()


def apply_laplacian(laplacian: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(V, V) sparse, (B, V, 3) -> (B, V, 3)."""
    B, V, _ = x.shape
    return torch.sparse.mm(laplacian, x.permute(1, 0, 2).reshape(V, B * 3)).reshape(V, B, 3).permute(1, 0, 2)


# -- the starting model ----------------------------------------------------------------------------

def initial_model(config: BodyConfig, data: BodyData, generator: torch.Generator | None = None,
                  shape_points: int = 1229, expression_points: int = 400, warmup_steps: int = 2000) -> BodyModel:
    """A BodyModel started from the data (see the module docstring); config's sizes that follow
    from the data (vertices, faces, rig, encoder points, expression vertices) are filled in."""
    generator = generator or torch.Generator().manual_seed(0)
    rest, joints = data.shape_rest.cpu(), data.shape_joints.cpu()
    template = rest.mean(0)
    basis = data.basis.cpu()
    moved = np.flatnonzero(basis.abs().amax(dim=(0, 2)).numpy() > 1e-7)
    points = np.sort(farthest_points(template.numpy(), shape_points))
    expression_subset = np.sort(farthest_points(template[moved].numpy(), expression_points))
    config = BodyConfig(**{**config.__dict__, "resolution": data.resolution, "num_vertices": len(template),
                           "num_faces": len(data.faces), "joint_names": tuple(data.joint_names),
                           "parents": tuple(data.parents), "shape_points": len(points),
                           "expression_vertices": len(moved), "expression_points": len(expression_subset)})
    body = BodyModel(config)
    with torch.no_grad():
        body.template.copy_(template)
        body.faces.copy_(torch.as_tensor(data.faces))
        for region, mask in data.regions.items():
            getattr(body, f"region_{region}").copy_(torch.as_tensor(mask))
        body.shape_points.copy_(torch.as_tensor(points))
        body.expression_index.copy_(torch.as_tensor(moved))
        body.expression_points.copy_(torch.as_tensor(expression_subset))
        centred = rest - template
        body.shape_scale.fill_(float(centred.std()))
        body.shape_vae.init_output_basis((centred / body.shape_scale).flatten(1))
        synthetic = torch.einsum("be,evc->bvc", random_activations(2000, len(basis), generator), basis)[:, moved]
        body.expression_scale.fill_(float(synthetic.std()))
        body.expression_vae.init_output_basis((synthetic / body.expression_scale).flatten(1))
        body.template_height.fill_(float(mesh_height(template[None])[0]))
        volume = mesh_volume(rest.double(), body.faces).float() * DENSITY
        mass = data.shape_mass.cpu()
        body.volume_scale.fill_(float((volume * mass).sum() / volume.square().sum()))
        height = data.shape_height.cpu()
        bmi = mass / height.square()
        body.height_range.copy_(torch.tensor([float(height.min()) - 0.05, float(height.max()) + 0.05]))
        body.weight_range.copy_(torch.tensor([float(mass.min()) * 0.9, float(mass.max()) * 1.1]))
        body.bmi_range.copy_(torch.tensor([float(bmi.min()) - 1.0, float(bmi.max()) + 1.5]))
        body.measurement_stats.copy_(torch.tensor([[float(height.mean()), float(height.std())],
                                                   [float(mass.mean()), float(mass.std())]]))
        body.skin.init_from(data.anny_weights, data.parents)
        body.limits.set_from(data.rotvec.cpu())
        support = joint_support(template.numpy(), joints.mean(0).numpy(), data.anny_weights, data.parents,
                                config.joint_support)
        body.joint_regressor.init_support(support)
    body.joint_regressor.fit(rest[:500], joints[:500])  # the training subjects first, then extra ones
    pretrain_vaes(body, rest, basis, generator, steps=warmup_steps)
    return body


def pretrain_vaes(body: BodyModel, rest: torch.Tensor, basis: torch.Tensor, generator: torch.Generator,
                  steps: int = 500, batch: int = 32, kl_weight: float = 0.01) -> dict[str, float]:
    """Warm the shape and expression VAEs up on their own reconstruction (rest meshes (N, V, 3);
    random facial-action mixes of basis (52, V, 3)) before the end-to-end training, so that
    starts from a decoder that already reproduces rest shapes. Returns the last errors (mm)."""
    parameters = list(body.shape_vae.parameters()) + list(body.expression_vae.parameters())
    optimizer = torch.optim.Adam(parameters, lr=1e-3)
    moved = body.expression_index
    errors = {}
    for _ in range(steps):
        rows = torch.randint(0, len(rest), (batch,), generator=generator)
        mu, logvar = body.encode_shape(rest[rows])
        decoded = body.decode_shape(VAE.sample_posterior(mu, logvar, generator))
        shape_error = ((decoded - rest[rows]).norm(dim=-1) * 1000).mean()
        offsets = torch.einsum("be,evc->bvc", random_activations(batch, len(basis), generator), basis)
        mu_e, logvar_e = body.encode_expression(offsets)
        decoded_e = body.decode_expression(VAE.sample_posterior(mu_e, logvar_e, generator))
        expression_error = ((decoded_e[:, moved] - offsets[:, moved]).norm(dim=-1) * 1000).mean()
        loss = (shape_error + expression_error
                + kl_weight * (kl_divergence(mu, logvar).mean() + kl_divergence(mu_e, logvar_e).mean()))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        errors = {"shape_mm": shape_error.item(), "expression_mm": expression_error.item()}
    return errors


def gaussian(x: torch.Tensor, jitter: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and Cholesky factor of the covariance of rows x (N, D)."""
    mean = x.mean(0)
    cov = torch.cov(x.T.double()) + jitter * torch.eye(x.shape[1], dtype=torch.float64, device=x.device)
    return mean, torch.linalg.cholesky(cov).to(x.dtype)


@torch.no_grad()
def calibrate(body: BodyModel, data: BodyData, ridge: float = 1e-2, expressions: int = 2000) -> None:
    """What the trained encoders define: the regressor from (height, weight) features to the shape
    latent means of the shape space's subjects (ridge regression), and Gaussians fitted to the
    latent means of those subjects and of random facial-action mixes (for sampling)."""
    mu = torch.cat([body.encode_shape(rest)[0] for rest in data.shape_rest.split(256)])
    features = measurement_features(data.shape_height, data.shape_mass, body.measurement_stats)
    gram = features.T @ features + ridge * torch.eye(features.shape[1], device=features.device)
    body.measurement_regressor.copy_(torch.linalg.solve(gram, features.T @ mu))
    mean, cholesky = gaussian(mu)
    body.shape_latent_mean.copy_(mean)
    body.shape_latent_cholesky.copy_(cholesky)
    activations = random_activations(expressions, data.basis.shape[0], torch.Generator().manual_seed(0))
    mu_e = body.encode_expression(data.offsets(activations.to(data.basis.device)))[0]
    mean, cholesky = gaussian(mu_e)
    body.expression_latent_mean.copy_(mean)
    body.expression_latent_cholesky.copy_(cholesky)


def finalize(weights: str, data_root: str, out: str, half: bool = False) -> BodyModel:
    """Calibrate trained weights (:func:`calibrate`, on the data folder they were trained on) and
    write them to `out` (half: float16 storage of the big matrices)."""
    from humotion.body.model import load_body_model

    body = load_body_model(weights)
    calibrate(body, BodyData(data_root, body.config.resolution))
    save_body_model(body, out, half=half, data=str(data_root), source=str(weights))
    return body


# -- training --------------------------------------------------------------------------------------

class BodyTrainer(nn.Module):
    """The body model plus the training meshes' pose parameters (buffers, so checkpoints keep
    them): pose_free (M, J, 3) unconstrained joint-limit parameters, translation (M, 3)."""

    def __init__(self, config: BodyTrainConfig, body: BodyModel, data: BodyData):
        super().__init__()
        self.config = config
        self.body = body
        self.data = data
        with torch.no_grad():
            self.register_buffer("pose_free", body.limits.to_free(data.rotvec))
            self.register_buffer("translation", data.translation.clone())
            self.register_buffer("template_joints", data.shape_joints.mean(0))
        self.laplacian = uniform_laplacian(data.faces, len(body.template)).to(data.vertices.device)

    def forward(self, rows: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, dict]:
        """Loss (a scalar tensor) and its terms by name (scalar tensors, mm for the distances) on
        training meshes `rows` ((N,) int64 indices; see the module docstring)."""
        d, body, w = self.data, self.body, self.config.weights
        shape_id = d.shape_id[rows]
        extra = torch.randint(0, len(d.shape_rest), (self.config.shape_batch,), generator=generator).to(rows.device)
        true_rest = torch.cat([d.rest_vertices[shape_id], d.shape_rest[extra]])
        true_joints = torch.cat([d.rest_joints[shape_id], d.shape_joints[extra]])
        mu, logvar = body.encode_shape(true_rest)
        rest, rest_joints = body.decode_shape_and_joints(VAE.sample_posterior(mu, logvar, generator))
        offsets = d.offsets(d.expression[rows])
        synthetic = random_activations(self.config.synthetic_expressions, d.basis.shape[0], generator).to(offsets.device)
        all_offsets = torch.cat([offsets, d.offsets(synthetic)])
        mu_e, logvar_e = body.encode_expression(all_offsets)
        expression = VAE.sample_posterior(mu_e, logvar_e, generator)
        rotations = body.limits.to_matrix(self.pose_free[rows])
        out = body(rest_vertices=rest[:len(rows)], expression=expression[:len(rows)], pose=rotations,
                   translation=self.translation[rows])
        moved = body.expression_index
        terms = {
            "posed": ((out.vertices - d.vertices[rows]).norm(dim=-1) * 1000).mean(),
            "rest": ((rest - true_rest).norm(dim=-1) * 1000).mean(),
            "expression": ((body.expression_moves(expression) - all_offsets[:, moved]).norm(dim=-1) * 1000).mean(),
            "joints": ((rest_joints - true_joints).norm(dim=-1) * 1000).mean(),
            "kl_shape": kl_divergence(mu, logvar).mean(),
            "kl_expression": kl_divergence(mu_e, logvar_e).mean(),
            "bones": bone_direction_loss(rest_joints, self.template_joints, body.parents),
            "sparsity": body.joint_regressor.l1(),
        }
        if body.correctives is not None:
            corrective = body.corrective_offsets(rotations, out.rest_vertices) * 1000
            terms["smooth"] = apply_laplacian(self.laplacian, corrective).square().sum(-1).mean()
            terms["corrective"] = corrective.square().sum(-1).mean()
        loss = sum(w[k] * v for k, v in terms.items())
        return loss, terms

    def reoptimise_poses(self) -> dict[str, float]:
        """L-BFGS on every training mesh's pose against the current model (see the module
        docstring); returns the mean error (mm) before and after."""
        d, body, c = self.data, self.body, self.config
        was_training = body.training
        body.eval()
        before, after = [], []
        for start in range(0, len(d), c.pose_batch):
            rows = torch.arange(start, min(start + c.pose_batch, len(d)), device=d.vertices.device)
            with torch.no_grad():
                mu, _ = body.encode_shape(d.rest_vertices[d.shape_id[rows]])
                rest = body.decode_shape(mu)
                expression, _ = body.encode_expression(d.offsets(d.expression[rows]))
            free, translation, b, a = fit_pose_to_vertices(body, d.vertices[rows], rest, self.pose_free[rows],
                                                           self.translation[rows], expression, c.pose_iterations)
            self.pose_free[rows] = free
            self.translation[rows] = translation
            before.append(b)
            after.append(a)
        body.train(was_training)
        result = {"pose_fit_before_mm": float(torch.cat(before).mean()), "pose_fit_after_mm": float(torch.cat(after).mean())}
        return result


def validate(body: BodyModel, held_out: dict[str, dict]) -> dict[str, float]:
    """Mean vertex errors (mm; all and per region) on held-out meshes with their given poses;
    "loss": the mean over the splits."""
    body.eval()
    result = {}
    for split, meshes in held_out.items():
        summary = summarise(vertex_errors(body, meshes), body)
        result.update({f"{split}/{k}": v for k, v in summary.items()})
    result["loss"] = float(np.mean([result[f"{split}/all"] for split in held_out]))
    body.train()
    return result


def train(config: BodyTrainConfig) -> dict:
    """Train (or resume) a body model; returns a summary dict (step, losses, validation, files)."""
    session = Session(config)
    device = session.device
    data = BodyData(config.data_root, config.resolution, device, config.validation_subjects)
    body = initial_model(config.model, data, warmup_steps=config.warmup_steps).to(device)
    config.model = body.config
    trainer = BodyTrainer(config, body, data).to(device)
    optimizer = torch.optim.Adam(body.parameters(), lr=config.lr)
    steps_per_epoch = math.ceil(math.ceil(len(data) / session.world) / config.batch_size)
    total = config.steps if config.steps is not None else config.epochs * steps_per_epoch
    validation = load_meshes(config.data_root, config.resolution, "train", shapes=data.validation_shapes)
    held_out = {"validation": {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in validation.items()}}
    session.echo(f"data: {len(data)} training meshes of {len(data.train_shapes)} subjects (+{data.extra_shapes} "
                 f"extra rest shapes), "
                 f"{data.vertices.shape[1]} vertices; {total} steps of {config.batch_size}")

    def batches(epoch: int, skip: int):
        if (skip == 0 and config.pose_every > 0 and epoch >= config.pose_start
                and (epoch - config.pose_start) % config.pose_every == 0):
            result = trainer.reoptimise_poses()
            session.log({"epoch": epoch, **result})
            session.echo(f"epoch {epoch}: poses re-optimised, {result['pose_fit_before_mm']:.2f} -> "
                         f"{result['pose_fit_after_mm']:.2f} mm")
        order = session.epoch_indices(len(data), epoch)
        for start in range(skip * config.batch_size, len(order), config.batch_size):
            yield torch.as_tensor(order[start:start + config.batch_size], device=device)

    def loss(model, rows):
        return model(rows, session.generator)

    def save_weights(module, path, **extra):
        calibrate(module.body, data)
        save_body_model(module.body, path, **extra)

    def lr_at(step: int) -> float:
        return learning_rate(step, total, config.lr, config.lr_final, config.lr_warmup)

    return fit(session, trainer, optimizer, steps_per_epoch=steps_per_epoch, batches=batches, loss=loss,
               validate=lambda module: validate(module.body, held_out), save_weights=save_weights,
               weights_name="body", lr_at=lr_at,
               describe=lambda val: f"validation subjects {val['validation/all']:.2f} mm")
