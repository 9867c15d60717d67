"""Registered training meshes for the learned body model, made from Anny and real mocap poses.

    python -m humotion.body.command data --out runs/body_data                 # 200 shapes x 8 poses
    python -m humotion.body.command data --out /tmp/tiny --shapes 4 --poses-per-shape 2

    data = load_split("runs/body_data", "full", "train")     # vertices (M, V, 3), shape_id, rotations, ...
    model = load_model_file("runs/body_data", "full")        # faces, rest shapes, skinning weights, masks

What a run makes (every step deterministic in --seed):

1. Shapes: Anny's phenotype sampler fitted to WHO statistics (ages 4-90, both sexes, thin to
   heavy; :func:`humotion.body.anny_source.sample_phenotypes`), with height, mass and BMI.
2. Poses: frames of the CMU mocap under ../shared/data/mocap, mapped onto humotion's 22-joint
   canonical body (:func:`humotion.canonical.to_canonical`), heading removed, then retargeted onto
   Anny's 76-joint rig (:func:`retarget`): each mapped rig bone gets the canonical joint's world
   rotation after a rest alignment that turns Anny's A-pose bones onto the mocap's T-pose bone
   directions, so posed bone directions match the mocap's exactly. Fingers get random curls and
   the eyes a random gaze; twist and in-between spine/neck bones follow their parents.
3. Expressions: about half the meshes get 1-4 of Anny's 52 ARKit-style facial actions.
4. Meshes: Anny's dual-quaternion skinning (which plain LBS cannot reproduce, so pose correctives
   have something to learn) on two topologies sharing the skeleton: "full" (13,718 vertices) and
   "low" (1,229). Posed meshes stand on the floor (lowest vertex at y = 0), pelvis above the origin.
5. Splits: held-out shapes x held-out poses (poses of held-out CMU subjects, the split of
   MotionCollection.split() that humotion's training uses): train / test_shapes / test_poses /
   test_both.

Folder layout (``np.load`` them without pickle; strings are unicode arrays):

- manifest.json: counts, seed, command, versions, timings, the LBS-vs-DQS gap, licences.
- shapes.npz: per shape: phenotypes (N, 6) + phenotype_names, age_years, height, mass, bmi,
  waist, volume, held_out (bool).
- poses.npz: per pose (one per mesh, pose_id = mesh_id): clip, frame, subject, held_out,
  canonical_rotations (P, 22, 4) (heading removed), finger_curl (P, 2, 5), gaze (P, 2) radians.
- {full,low}/model.npz: faces (faces, 3) int32, joint_names, parents, rest_vertices (N, V, 3) and
  rest_joints (N, J, 3) per shape (neutral expression, Anny's origin), skin_weights (V, J)
  (Anny's LBS weights), expression_basis (52, V, 3) + facial_action_names, part (V,) labels +
  part_names, region_body / region_face / region_hands (V,) bool.
- {full,low}/{split}.npz: per mesh: vertices (M, V, 3) float32 metres, mesh_id, shape_id,
  pose_id, rotations (M, J, 4) wxyz, translation (M, 3), joints (M, J, 3) posed joint centres,
  expression (M, 52), lbs_gap_mm (M,) (full only: mean distance of plain LBS from the DQS mesh).

Pose parameters: ``rotations`` are each joint's rest-relative rotation expressed in world-aligned
rest axes (SMPL-style): world rotation A_j = A_parent(j) @ R_j, posed joint
p_j = p_parent + A_parent (rest_j - rest_parent), root p_0 = rest_0 + translation, skinning
transform x -> A_j (x - rest_j) + p_j. :mod:`humotion.body.skinning` implements it;
vertices = DQS of (rest_vertices + expression offsets) under those transforms. Expression offsets: ``expression @ expression_basis`` (a rest-pose,
neutral-head-pose offset: the expressive rest mesh minus the neutral one).

Modules: this one plans and generates; :mod:`humotion.body.posing` retargets mocap poses onto the
rig and samples poses and expressions; :mod:`humotion.body.skinning` holds the kinematics and LBS;
:mod:`humotion.body.files` writes and reads the folder; :mod:`humotion.body.anny_source` wraps Anny;
:mod:`humotion.body.command` holds the command line.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.body.files import (RESOLUTIONS, SPLITS, load_model_file, load_npz, load_poses, load_shapes,
                                 load_split, read_manifest, save_json, save_npz)
from humotion.body.posing import (aim_errors, hand_and_eye_rotations, reach_errors, retarget, rig_points,
                                  sample_expressions, sample_hand_and_gaze, sample_mocap_poses)
from humotion.body.skinning import blend_zones, linear_blend_skinning, skinning_transforms
from humotion.canonical import JOINTS
from humotion.data import default_data_dir

__all__ = ["Settings", "Plan", "plan_splits", "draw_mocap_poses", "Generator", "generate", "SPLITS",
           "RESOLUTIONS", "load_split", "load_model_file", "load_shapes", "load_poses", "read_manifest"]

log = logging.getLogger("humotion.body.dataset")

DEFAULT_MOCAP = default_data_dir() / "mocap"
EXCLUDED_SOURCES = ("hdm05_jointlearning", "cmu_iclone_ccskeleton")
"""Mocap sources not used for poses: HDM05 is evaluation-only (CC BY-SA); the iClone set holds
game-rig copies of CMU takes whose zero pose is no T-pose."""

LOW_TOPOLOGIES = ("notoes_collapse10pc", "notoes_collapse5pc", "notoes_collapse3pc", "none")
"""Settings.topology's choices: Anny topologies of 1,229 / 615 / 369 vertices, or no low resolution."""

FORMAT_VERSION = 1
LICENCE = ("Meshes generated with Anny (NAVER, https://github.com/naver/anny): code Apache-2.0, "
           "body model assets derived from MakeHuman, CC0. Poses from the CMU Graphics Lab Motion "
           "Capture Database (mocap.cs.cmu.edu), funded by NSF EIA-0196217.")


# -- splits ------------------------------------------------------------------------------------

@dataclass
class Plan:
    """Which shape and which kind of pose every mesh gets, and its split.

    shape_held_out (N,) bool; mesh_shape (M,) shape index; mesh_pose_held_out (M,) bool;
    mesh_split (M,) index into SPLITS. Mesh m = shape m // K, its k-th pose m % K."""

    shape_held_out: np.ndarray
    mesh_shape: np.ndarray
    mesh_pose_held_out: np.ndarray
    mesh_split: np.ndarray


def plan_splits(num_shapes: int, poses_per_shape: int, rng: np.random.Generator,
                held_out_shapes: float = 0.1, held_out_poses: int | None = None) -> Plan:
    """Hold out round(held_out_shapes * N) shapes (at least one when N >= 2) and, for every shape,
    its last held_out_poses poses (default: K // 8, at least one when K >= 2) drawn from held-out
    mocap subjects. Each mesh's split follows from the two: see SPLITS."""
    n_shapes = round(held_out_shapes * num_shapes)
    if held_out_shapes > 0 and num_shapes >= 2:
        n_shapes = min(max(n_shapes, 1), num_shapes - 1)
    if held_out_poses is None:
        held_out_poses = max(poses_per_shape // 8, 1) if poses_per_shape >= 2 else 0
    if not 0 <= held_out_poses <= poses_per_shape:
        raise ValueError(f"held_out_poses must be in [0, {poses_per_shape}], got {held_out_poses}")
    shape_held = np.zeros(num_shapes, dtype=bool)
    shape_held[rng.choice(num_shapes, size=n_shapes, replace=False)] = True
    mesh_shape = np.repeat(np.arange(num_shapes), poses_per_shape)
    pose_held = np.tile(np.arange(poses_per_shape) >= poses_per_shape - held_out_poses, num_shapes)
    split = shape_held[mesh_shape].astype(np.int64) + 2 * pose_held.astype(np.int64)
    return Plan(shape_held, mesh_shape, pose_held, split)


# -- generation ----------------------------------------------------------------------------------

def draw_mocap_poses(mocap: str | Path, held_out: np.ndarray, rng: np.random.Generator,
                     progress: bool = False) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """One mocap pose per mesh and the subject split of the collection under `mocap`.

    held_out: (M,) bool, True where the mesh's pose comes from the test subjects' clips, False
    from the training subjects' (EXCLUDED_SOURCES left out). Returns the MocapPoses fields
    stacked over the M meshes (clip names relative to the collection's root, which is `mocap`
    with its symlinks resolved) and MotionCollection.split()."""
    from humotion.data import MotionCollection

    collection = MotionCollection.load(mocap, progress=progress)
    subjects = collection.split()
    usable = collection.filter(exclude=EXCLUDED_SOURCES)
    pools = {False: usable.filter(subjects=subjects["train"]).clips, True: usable.filter(subjects=subjects["test"]).clips}
    poses = [None] * len(held_out)
    for held in (False, True):
        rows = np.flatnonzero(held_out == held)
        if len(rows):
            drawn = sample_mocap_poses(pools[held], len(rows), rng, root=collection.root)
            for i, row in enumerate(rows):
                poses[row] = {k: np.asarray(getattr(drawn, k)[i]) for k in drawn.__dataclass_fields__}
    return {k: np.stack([p[k] for p in poses]) for k in poses[0]}, subjects


@dataclass
class Settings:
    """One run's settings (they key its resume state)."""

    out: str
    """Output folder (resumes a run there)."""
    shapes: int = 200
    """Body shapes (phenotypes) to draw."""
    poses_per_shape: int = 8
    """Posed meshes per shape."""
    seed: int = 0
    """Seed of every random draw (shapes, poses, expressions, splits)."""
    topology: str = "notoes_collapse10pc"
    """Anny topology of the low resolution (1,229 / 615 / 369 vertices), or none."""
    mocap: str = str(DEFAULT_MOCAP)
    """Mocap folder tree the poses come from."""
    held_out_shapes: float = 0.1
    """Fraction of shapes held out."""
    held_out_poses: int | None = None
    """Poses per shape from held-out subjects (default K // 8, >= 1)."""
    expression_fraction: float = 0.5
    """Share of meshes with a facial expression."""
    min_age: float = 4.0
    """Youngest morphological age (years)."""
    max_age: float = 90.0
    """Oldest morphological age (years)."""
    chunk: int = 10
    """Shapes per resumable chunk."""

    def key(self) -> str:
        fields = {k: v for k, v in self.__dict__.items() if k not in ("out", "chunk")}
        return hashlib.sha1(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


class Generator:
    """A data run: the plan (shapes, poses, expressions, splits), then meshes chunk by chunk into
    OUT/.parts (kept on an interrupted run and reused by the next one with the same settings),
    then the final files."""

    def __init__(self, settings: Settings, command: str = "", progress: bool = True):
        from humotion.body import anny_source

        self.settings, self.command, self.progress = settings, command, progress
        self.out = Path(settings.out)
        self.timings: dict[str, float] = {}
        start = time.perf_counter()
        self.bodies = {"full": anny_source.AnnyBody(anny_source.TOPOLOGIES["full"])}
        self.timings["build_full_s"] = time.perf_counter() - start
        if settings.topology and settings.topology != "none":
            start = time.perf_counter()
            self.bodies["low"] = anny_source.AnnyBody(settings.topology)
            self.timings["build_low_s"] = time.perf_counter() - start
        full = self.bodies["full"]
        for name, body in self.bodies.items():
            if body.joint_names != full.joint_names or body.parents != full.parents:
                raise RuntimeError(f"the {name} topology's rig differs from the full one's")
        self.names, self.parents = full.joint_names, full.parents
        self.anny_source = anny_source

    # -- the plan --------------------------------------------------------------------------
    def make_plan(self) -> dict:
        s = self.settings
        rng = np.random.default_rng(s.seed)
        full = self.bodies["full"]
        phenotypes, ages = self.anny_source.sample_phenotypes(full, s.shapes, s.seed, s.min_age, s.max_age)
        plan = plan_splits(s.shapes, s.poses_per_shape, rng, s.held_out_shapes, s.held_out_poses)
        start = time.perf_counter()
        poses, subjects = draw_mocap_poses(s.mocap, plan.mesh_pose_held_out, rng, self.progress)
        self.timings["mocap_poses_s"] = time.perf_counter() - start
        count = len(plan.mesh_shape)
        curl, gaze = (x.numpy() for x in sample_hand_and_gaze(rng, count))
        expression = sample_expressions(rng, count, len(full.facial_action_names), s.expression_fraction).numpy()
        return dict(plan=plan, phenotypes=phenotypes, ages=ages, poses=poses, curl=curl, gaze=gaze,
                    expression=expression, subjects=subjects)

    # -- one chunk of shapes ---------------------------------------------------------------
    def make_chunk(self, plan: dict, shapes: range) -> dict[str, np.ndarray]:
        """The meshes of the plan's shapes `shapes`, as arrays over their M meshes: rows (M,) mesh
        ids, rotations (M, J, 4) wxyz float32, translation (M, 3) and joints (M, J, 3) metres,
        vertices_{full,low} (M, V, 3) metres, gap_{region} and gap_all (M,) metres (plain LBS from
        the DQS mesh), aim_{joint} and reach_{point} (M,) degrees; and per shape of the chunk (N of
        them) rest_vertices_{full,low} (N, V, 3) and rest_joints (N, J, 3), metres."""
        full = self.bodies["full"]
        weights = full.skin_weights()
        zones = blend_zones(weights, self.names, self.parents)
        basis = full.expression_basis()
        out: dict[str, list] = {}

        def add(key, value):
            out.setdefault(key, []).append(value)

        for shape in shapes:
            rows = np.flatnonzero(plan["plan"].mesh_shape == shape)
            pheno = plan["phenotypes"][shape:shape + 1]
            rests = {name: body.rest(pheno) for name, body in self.bodies.items()}
            rest_v, rest_j = rests["full"].vertices[0], rests["full"].joints[0]
            for name, rest in rests.items():
                if np.abs(rest.joints[0] - rest_j).max() > 1e-4:
                    raise RuntimeError(f"{name} topology's joints differ from the full one's for shape {shape}")
            points = rig_points(torch.from_numpy(rest_v), torch.from_numpy(rest_j), self.names)
            world, canonical_rest, canonical_posed = (torch.from_numpy(plan["poses"][k][rows])
                                                      for k in ("world_rotations", "rest", "posed"))
            extra = hand_and_eye_rotations(torch.from_numpy(rest_j), self.names, torch.from_numpy(plan["curl"][rows]),
                                           torch.from_numpy(plan["gaze"][rows]))
            local = retarget(world, canonical_rest, points, self.names, self.parents, extra).numpy()
            expression = plan["expression"][rows]
            translation = np.zeros((len(rows), 3))
            translation[:, [0, 2]] = -rest_j[0, [0, 2]]
            vertices = {"full": full.pose(pheno, expression, local, translation)}
            floor = -vertices["full"][..., 1].min(1)
            translation[:, 1] += floor
            vertices["full"][..., 1] += floor[:, None]
            for name, body in self.bodies.items():
                if name != "full":
                    vertices[name] = body.pose(pheno, expression, local, translation)
            A, t, joints = skinning_transforms(rest_j, self.parents, local, translation)
            lbs = linear_blend_skinning(rest_v + np.einsum("ke,evc->kvc", expression, basis), weights, A, t)
            gap = np.linalg.norm(lbs - vertices["full"], axis=-1)
            for region, zone in zones.items():
                add(f"gap_{region}", gap[:, zone].mean(1))
            add("gap_all", gap.mean(1))
            for joint, error in aim_errors(torch.from_numpy(A), torch.from_numpy(joints), points, self.names, world,
                                           canonical_rest).items():
                add(f"aim_{joint}", error.numpy())
            for point, error in reach_errors(torch.from_numpy(A), torch.from_numpy(joints), points, self.names,
                                             canonical_posed).items():
                add(f"reach_{point}", error.numpy())
            add("rows", rows)
            add("rotations", rot.matrix_to_quat(torch.as_tensor(local)).numpy().astype(np.float32))
            add("translation", translation.astype(np.float32))
            add("joints", joints.astype(np.float32))
            for name, v in vertices.items():
                add(f"vertices_{name}", v.astype(np.float32))
            for name, rest in rests.items():
                add(f"rest_vertices_{name}", rest.vertices.astype(np.float32))
            add("rest_joints", rest_j[None].astype(np.float32))
        return {k: np.concatenate(v) for k, v in out.items()}

    # -- the whole run ---------------------------------------------------------------------
    def run(self) -> dict:
        s = self.settings
        self.out.mkdir(parents=True, exist_ok=True)
        parts = self.out / ".parts"
        state = parts / "settings.json"
        if parts.exists() and (not state.exists() or json.loads(state.read_text()).get("key") != s.key()):
            log.info("discarding the parts of a run with other settings in %s", parts)
            shutil.rmtree(parts)
        parts.mkdir(exist_ok=True)
        save_json(state, {"key": s.key(), "settings": s.__dict__})

        start = time.perf_counter()
        plan = self.make_plan()
        self.timings["plan_s"] = time.perf_counter() - start
        chunks = [range(a, min(a + s.chunk, s.shapes)) for a in range(0, s.shapes, s.chunk)]
        start, made = time.perf_counter(), 0
        bar = tqdm(total=len(plan["plan"].mesh_shape), desc="body meshes", unit="mesh", disable=not self.progress)
        results = []
        for i, shapes in enumerate(chunks):
            path = parts / f"chunk-{i:04d}.npz"
            if path.exists():
                results.append(load_npz(path))
            else:
                result = self.make_chunk(plan, shapes)
                save_npz(path, result)
                results.append(result)
                made += len(result["rows"])
            bar.update(len(results[-1]["rows"]))
        bar.close()
        elapsed = time.perf_counter() - start
        self.timings["meshes_s"] = elapsed
        self.timings["per_mesh_s"] = elapsed / made if made else float("nan")
        chunk = {k: np.concatenate([r[k] for r in results]) for k in results[0]}
        manifest = self.write(plan, chunk)
        shutil.rmtree(parts)
        return manifest

    def write(self, plan: dict, chunk: dict[str, np.ndarray]) -> dict:
        """The folder's files (see the module docstring) from the plan and every chunk's arrays
        concatenated (:meth:`make_chunk`: rows (M,) of all meshes in order, vertices_full
        (M, V, 3), ...); returns the manifest written."""
        s, full = self.settings, self.bodies["full"]
        p = plan["plan"]
        if not np.array_equal(chunk["rows"], np.arange(len(p.mesh_shape))):
            raise RuntimeError("chunks do not cover the meshes in order: delete OUT/.parts and run again")
        rest_full = chunk["rest_vertices_full"]
        measures = full.anthropometry(rest_full.astype(np.float64))
        save_npz(self.out / "shapes.npz", dict(
            shape_id=np.arange(s.shapes), phenotypes=plan["phenotypes"].astype(np.float32),
            phenotype_names=np.array(full.phenotype_names), age_years=plan["ages"].astype(np.float32),
            held_out=p.shape_held_out, **{k: v.astype(np.float32) for k, v in measures.items()}))
        poses = plan["poses"]
        save_npz(self.out / "poses.npz", dict(
            pose_id=np.arange(len(p.mesh_shape)), clip=poses["clip"], frame=poses["frame"], subject=poses["subject"],
            held_out=p.mesh_pose_held_out, canonical_rotations=poses["local"].astype(np.float32),
            canonical_joint_names=np.array(JOINTS), finger_curl=plan["curl"].astype(np.float32),
            gaze=plan["gaze"].astype(np.float32)))

        labels, label_names = full.part_labels()
        template_full = full.template_vertices()
        sizes = {}
        for name, body in self.bodies.items():
            part = labels if name == "full" else self.anny_source.transfer_labels(template_full, labels, body.template_vertices())
            regions = {f"region_{r}": np.isin(part, [label_names.index(x) for x in parts])
                       for r, parts in self.anny_source.REGION_PARTS.items()}
            folder = self.out / name
            save_npz(folder / "model.npz", dict(
                faces=body.faces, joint_names=np.array(self.names), parents=np.array(self.parents),
                rest_vertices=chunk[f"rest_vertices_{name}"], rest_joints=chunk["rest_joints"],
                skin_weights=body.skin_weights(), expression_basis=body.expression_basis(),
                facial_action_names=np.array(body.facial_action_names), part=part, part_names=np.array(label_names),
                **regions))
            for k, split in enumerate(SPLITS):
                rows = np.flatnonzero(p.mesh_split == k)
                arrays = dict(vertices=chunk[f"vertices_{name}"][rows], mesh_id=rows, shape_id=p.mesh_shape[rows],
                              pose_id=rows, rotations=chunk["rotations"][rows], translation=chunk["translation"][rows],
                              joints=chunk["joints"][rows], expression=plan["expression"][rows].astype(np.float32))
                if name == "full":
                    arrays["lbs_gap_mm"] = (chunk["gap_all"][rows] * 1000).astype(np.float32)
                save_npz(folder / f"{split}.npz", arrays)
            sizes[name] = dict(vertices=body.num_vertices, faces=len(body.faces))

        counts = {split: int((p.mesh_split == k).sum()) for k, split in enumerate(SPLITS)}
        gap = {region[4:]: round(float(chunk[region].mean() * 1000), 3) for region in chunk if region.startswith("gap_")}
        gap_max = round(float(chunk["gap_all"].max() * 1000), 3)
        aims = {k[4:]: round(float(np.percentile(v, 99)), 4) for k, v in chunk.items() if k.startswith("aim_")}
        reach = {k[6:]: [round(float(np.percentile(v, q)), 2) for q in (50, 90, 99)] for k, v in chunk.items()
                 if k.startswith("reach_")}
        manifest = dict(
            format_version=FORMAT_VERSION, command=self.command, seed=s.seed, settings=s.__dict__,
            anny_version=self.anny_source.anny_version(), rig=self.anny_source.DEFAULT_RIG,
            topologies={name: body.topology for name, body in self.bodies.items()}, resolutions=sizes,
            joints=len(self.names), shapes=s.shapes, held_out_shapes=int(p.shape_held_out.sum()),
            poses_per_shape=s.poses_per_shape, meshes=len(p.mesh_shape), splits=counts,
            mocap_subjects={"train": plan["subjects"]["train"], "held_out": plan["subjects"]["test"]},
            excluded_sources=list(EXCLUDED_SOURCES),
            expressive_meshes=int((plan["expression"] > 0).any(1).sum()),
            lbs_vs_dqs_mean_mm=gap, lbs_vs_dqs_worst_mesh_mm=gap_max,
            retarget_aim_error_deg_p99=aims, retarget_limb_error_deg_p50_p90_p99=reach,
            timings_s={k: round(v, 3) for k, v in self.timings.items()},
            bytes=None, licence=LICENCE,
            conventions="metres, Y up, characters face +Z, quaternions wxyz; see humotion/body/dataset.py")
        manifest["bytes"] = sum(f.stat().st_size for f in self.out.rglob("*.npz") if ".parts" not in f.parts)
        save_json(self.out / "manifest.json", manifest)
        return manifest


def generate(settings: Settings, command: str = "", progress: bool = True) -> dict:
    """Make a data folder (see the module docstring); returns the manifest."""
    return Generator(settings, command, progress).run()

