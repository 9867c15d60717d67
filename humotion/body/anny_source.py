"""Everything of humotion that touches Anny, the open body model the training meshes come from.

Anny (NAVER, https://github.com/naver/anny; code Apache-2.0, MakeHuman-derived assets CC0) is
an optional extra (``pip install humotion[anny]``), used only to build data: nothing that ships
with humotion imports it at run time. This module wraps the few calls the data generator needs
and converts Anny's conventions to humotion's at the boundary:

- Anny: Z up, characters face -Y, left +X, metres, float64. humotion: Y up, face +Z, left +X.
  ``p_humotion = ANNY_TO_HUMOTION @ p_anny`` (a -90 degree turn about X).
- Poses are given here as humotion-style rest-relative *world-aligned* local rotations L (J, 3, 3)
  and a root translation; :func:`humotion.body.skinning.skinning_transforms` turns them into
  per-bone transforms T_j = [A_j | t_j] (A_j = A_parent L_j). Anny is posed with its "world"
  pose parameterisation, bone world poses W_j = T_j P_j (P_j: Anny's rest bone pose), so the
  skinning transforms Anny uses are exactly T_j, whatever Anny's rest bone orientations are.

    body = AnnyBody("anny")                       # 13,718 vertices; "notoes_collapse10pc": 1,229
    rest = body.rest(phenotypes)                  # rest vertices / joints per shape, humotion frame
    verts = body.pose(phenotypes, expression, rotations, translation)   # dual-quaternion skinning

Build times (2-core CPU): the first model ever built writes ~0.8 GB to the Anny cache
($ANNY_CACHE_DIR, default ~/.cache/anny) in ~4 min; any other rig / topology then takes ~15 s
the first time and well under a second from the cache afterwards.
"""

from __future__ import annotations

import importlib.metadata
import os
from dataclasses import dataclass

import numpy as np
import torch

ANNY_TO_HUMOTION = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking Anny's Z-up, -Y-facing frame to humotion's Y-up, +Z-facing frame."""

DEFAULT_RIG = "anny-notoes"
"""Anny's default rig without its 28 toe bones (their skinning weights merged into the feet):
76 joints (body with twist bones, 2 x 19 finger bones, neck x 3, head, eyes). The low-resolution
topologies have no toes, so this is the one skeleton both resolutions share."""

TOPOLOGIES = {"full": "anny", "low": "notoes_collapse10pc"}
"""Resolution name -> Anny topology: 13,718 and 1,229 vertices (notoes_collapse3pc / 5pc have
369 / 615). All share the rig, phenotypes and facial actions."""

REGION_PARTS = {
    "body": ("body", "foot.L", "foot.R"),
    "face": ("head", "eye_back.L", "eye_front.L", "eye_back.R", "eye_front.R", "eye_cavity.L",
             "eye_cavity.R", "mouth_cavity", "tongue"),
    "hands": ("hand.L", "hand.R"),
}
"""Regions of the evaluation (body, face, hands) as unions of Anny's segmentation labels
(anny/data/segmentation/body_parts_segmentation.yaml; 'head' is the whole head)."""


def anny_version() -> str | None:
    """The installed Anny's version, or None when it is not installed."""
    try:
        return importlib.metadata.version("anny")
    except importlib.metadata.PackageNotFoundError:
        return None


def _import_anny(cache_dir: str | None = None):
    """Import anny, pointing its model cache at cache_dir (or $ANNY_CACHE_DIR) first. An empty
    $ANNY_CACHE_DIR counts as unset (anny would write its ~1 GB cache into the working directory)."""
    if cache_dir:
        os.environ["ANNY_CACHE_DIR"] = str(cache_dir)
    elif os.environ.get("ANNY_CACHE_DIR") == "":
        del os.environ["ANNY_CACHE_DIR"]
    try:
        import anny
        import anny.paths
    except ImportError as error:
        raise ImportError("generating body data needs Anny: pip install 'humotion[anny]' (anny==0.6.2)") from error
    if cache_dir:
        anny.paths.set_anny_cache_path(cache_dir)
    return anny


def _to_humotion(x: torch.Tensor) -> np.ndarray:
    """(..., 3) Anny-frame points -> humotion frame, float64 numpy."""
    return x.detach().double().cpu().numpy() @ ANNY_TO_HUMOTION.T


@dataclass
class RestShapes:
    """Rest (A-pose) bodies in humotion's frame, float64: vertices (N, V, 3), joints (N, J, 3)
    (Anny's bone heads: the joint centres), bone_poses (N, J, 4, 4) (Anny's rest bone poses, in
    Anny's frame; needed only to pose Anny). The origin is Anny's: the root joint (pelvis) sits
    near it, the soles ~0.8 m below for an adult."""

    vertices: np.ndarray
    joints: np.ndarray
    bone_poses: torch.Tensor


class AnnyBody:
    """One Anny model (a topology, the shared rig, all 52 facial actions, dual-quaternion skinning).

    topology: an Anny topology name ("anny", "notoes_collapse10pc", ...). rig: an Anny rig spec.
    cache_dir: Anny's model cache (default $ANNY_CACHE_DIR or ~/.cache/anny).
    """

    def __init__(self, topology: str = "anny", rig: str = DEFAULT_RIG, cache_dir: str | None = None):
        anny = _import_anny(cache_dir)
        self.topology, self.rig = topology, rig
        self.model = anny.Anny(rig=rig, topology=topology, facial_actions="all", skinning_method="dqs")
        self.model.requires_grad_(False)
        self.joint_names: list[str] = list(self.model.bone_labels)
        self.parents: list[int] = [int(p) for p in self.model.bone_parents]
        self.phenotype_names: list[str] = list(self.model.phenotype_labels)
        self.facial_action_names: list[str] = list(self.model.facial_action_labels)
        self.faces = self.model.faces.cpu().numpy().astype(np.int32)
        self.num_vertices = int(self.model.template_vertices.shape[0])

    # -- fixed data ---------------------------------------------------------------------------
    def skin_weights(self) -> np.ndarray:
        """(V, J) float32 Anny's linear-blend skinning weights (rows sum to 1)."""
        weights = torch.zeros(self.num_vertices, len(self.joint_names), dtype=torch.float64)
        weights.scatter_add_(1, self.model.vertex_bone_indices.long(), self.model.vertex_bone_weights.double())
        return weights.numpy().astype(np.float32)

    def expression_basis(self) -> np.ndarray:
        """(52, V, 3) float32 vertex offsets of the facial actions at activation 1 (humotion frame).

        Anny adds them linearly to the rest shape, the same for every phenotype, so a mesh's
        expression offsets are ``expression @ basis`` (checked in the tests)."""
        labels = list(self.model.blendshape_labels)
        rows = [labels.index(f"facial_action:{name}") for name in self.facial_action_names]
        return _to_humotion(self.model.blendshapes[rows]).astype(np.float32)

    def template_vertices(self) -> np.ndarray:
        """(V, 3) the rest mesh at the default phenotypes (all 0.5), humotion frame."""
        return self.rest(np.full((1, len(self.phenotype_names)), 0.5)).vertices[0]

    def part_labels(self) -> tuple[np.ndarray, list[str]]:
        """Per-vertex body-part label (V,) int16 and the label names, from Anny's UV-space
        segmentation: each vertex takes the most common label of the faces around it. Only for
        topologies with texture coordinates (the full one); see :func:`transfer_labels`."""
        import yaml
        from anny.face_segmentation import get_face_segmentation_mask
        from anny.paths import get_anny_root_dir

        if self.model.texture_coordinates is None:
            raise ValueError(f"topology {self.topology!r} has no texture coordinates; transfer labels from 'anny'")
        with open(get_anny_root_dir() / "data/segmentation/body_parts_segmentation.yaml") as f:
            names = list(yaml.safe_load(f)["colors"])
        face_label = np.full(len(self.faces), -1, dtype=np.int64)
        for k, name in enumerate(names):
            face_label[get_face_segmentation_mask(self.model, [name]).cpu().numpy()] = k
        if (face_label < 0).any():  # a colour between two labels: the body
            face_label[face_label < 0] = names.index("body")
        counts = np.zeros((self.num_vertices, len(names)), dtype=np.int64)
        for corner in range(self.faces.shape[1]):
            np.add.at(counts, (self.faces[:, corner], face_label), 1)
        return counts.argmax(1).astype(np.int16), names

    def anthropometry(self, rest_vertices: np.ndarray) -> dict[str, np.ndarray]:
        """Anny's measurements of rest meshes (N, V, 3) in humotion's frame (full topology only):
        height (m), mass (kg, volume x 980 kg/m^3), bmi, waist circumference (m), volume (m^3)."""
        import anny

        measure = anny.Anthropometry(self.model)
        anny_frame = torch.as_tensor(rest_vertices @ ANNY_TO_HUMOTION, dtype=self.model.dtype)
        return {k: v.double().cpu().numpy() for k, v in measure(anny_frame).items()}

    # -- shapes and poses ---------------------------------------------------------------------
    def _phenotypes(self, phenotypes: np.ndarray) -> torch.Tensor:
        phenotypes = np.array(phenotypes, dtype=np.float64)
        if phenotypes.ndim != 2 or phenotypes.shape[1] != len(self.phenotype_names):
            raise ValueError(f"phenotypes must be (N, {len(self.phenotype_names)}) in the order {self.phenotype_names}")
        return torch.as_tensor(phenotypes, dtype=self.model.dtype)

    def _expression(self, expression: np.ndarray | None, count: int) -> torch.Tensor:
        if expression is None:
            return torch.zeros(count, len(self.facial_action_names), dtype=self.model.dtype)
        return torch.as_tensor(np.array(expression, dtype=np.float64), dtype=self.model.dtype).reshape(count, -1)

    def rest(self, phenotypes: np.ndarray, expression: np.ndarray | None = None) -> RestShapes:
        """Rest bodies of phenotypes (N, 6) (columns: self.phenotype_names, each in [0, 1]) with
        facial action activations (N, 52) (None: neutral)."""
        pheno = self._phenotypes(phenotypes)
        out = self.model(phenotype_kwargs=pheno, facial_actions=self._expression(expression, len(pheno)))
        return RestShapes(_to_humotion(out["rest_vertices"]), _to_humotion(out["rest_bone_heads"]),
                          out["rest_bone_poses"])

    def pose(self, phenotypes: np.ndarray, expression: np.ndarray | None, rotations: np.ndarray,
             translation: np.ndarray, skinning: str = "dqs") -> np.ndarray:
        """Posed vertices (K, V, 3) float64, humotion frame.

        phenotypes (6,) or (K, 6); expression (K, 52) or None; rotations (K, J, 3, 3) world-aligned
        rest-relative local rotations (see module docstring); translation (K, 3) of the root joint
        from its rest position. skinning: "dqs" (Anny's dual-quaternion skinning) or "lbs"."""
        from humotion.body.skinning import skinning_transforms

        rotations = np.asarray(rotations, dtype=np.float64)
        count = len(rotations)
        pheno = np.broadcast_to(np.asarray(phenotypes, dtype=np.float64).reshape(-1, len(self.phenotype_names)),
                                (count, len(self.phenotype_names)))
        rest = self.rest(pheno, expression)
        A, t, _ = skinning_transforms(rest.joints, self.parents, rotations, translation)
        # Bone world poses W = T P in Anny's frame: T_anny = C^T T C for C = ANNY_TO_HUMOTION.
        C = torch.as_tensor(ANNY_TO_HUMOTION, dtype=self.model.dtype)
        T = torch.zeros(count, len(self.parents), 4, 4, dtype=self.model.dtype)
        T[..., :3, :3] = C.T @ torch.as_tensor(A, dtype=self.model.dtype) @ C
        T[..., :3, 3] = torch.as_tensor(t, dtype=self.model.dtype) @ C
        T[..., 3, 3] = 1.0
        world = T @ rest.bone_poses
        self.model.set_skinning_method(skinning)
        try:
            out = self.model(pose_parameters=world, phenotype_kwargs=self._phenotypes(pheno),
                             facial_actions=self._expression(expression, count), pose_parameterization="world")
        finally:
            self.model.set_skinning_method("dqs")
        return _to_humotion(out["vertices"])


def sample_phenotypes(model: AnnyBody, count: int, seed: int, min_age: float = 4.0,
                      max_age: float = 90.0) -> tuple[np.ndarray, np.ndarray]:
    """(phenotypes (count, 6) in model.phenotype_names order, morphological age in years (count,)).

    Anny's SimpleShapeDistribution, calibrated on WHO height/weight-for-age statistics: age
    uniform in [min_age, max_age] years, gender uniform in [0, 1] (0 male, 1 female), height,
    weight, muscle and proportions drawn from age- and sex-conditional Beta distributions.
    Deterministic in seed (torch's global generator is seeded, then restored)."""
    from anny.shape_distribution import SimpleShapeDistribution

    dtype = model.model.dtype
    state = torch.random.get_rng_state()
    try:
        torch.manual_seed(seed)
        ages = torch.distributions.Uniform(torch.tensor(float(min_age), dtype=dtype), torch.tensor(float(max_age), dtype=dtype))
        sampler = SimpleShapeDistribution(model.model, morphological_age_distribution=ages)
        age_years, values = sampler.sample(count)
    finally:
        torch.random.set_rng_state(state)
    phenotypes = np.stack([values[name].double().numpy() for name in model.phenotype_names], axis=1)
    return np.clip(phenotypes, 0.0, 1.0), age_years.double().numpy()


def transfer_labels(source_vertices: np.ndarray, source_labels: np.ndarray, target_vertices: np.ndarray) -> np.ndarray:
    """(V_t,) labels of target vertices (V_t, 3) from the nearest of the source vertices (V_s, 3),
    whose labels are source_labels (V_s,) (two meshes of one body, metres); dtype of the labels."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(source_vertices).query(target_vertices)
    return source_labels[nearest]
