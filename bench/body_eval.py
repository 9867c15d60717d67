"""Benchmark of the learned body model on the held-out meshes of a body data folder.

    python bench/body_eval.py                                   # shipped weights, runs/body_data
    python bench/body_eval.py --low runs/body/low/body.pt --full runs/body/full/body.pt --json out.json
    python bench/body_eval.py --skip-curve --skip-speed         # the error tables only
    python bench/body_eval.py --resolution full                 # one resolution (no shape curve without low)

Tables (markdown; mean per-vertex distance to the registered mesh in mm):

1. Held-out error per region (body, face, hands) and per joint blend zone, both resolutions, on
   test_shapes (held-out subjects), test_poses (held-out mocap subjects' poses) and test_both,
   with the data's pose parameters ("given") and with poses refitted by L-BFGS within the joint
   limits ("fitted"). Shape / expression latents: the encoders' means for the subject's rest
   mesh / the expression offsets (humotion.body.evaluation). Rows "true rest mesh" pose the
   subject's actual rest mesh instead of the decoded one, isolating the shape space's share.
2. Shape space: the shape VAE vs PCA across latent sizes on the held-out subjects' rest meshes
   (low resolution). The VAEs of the curve are trained alone (same architecture and start as the
   model's, --curve-steps Adam steps on the training subjects' rest shapes, extra rest shapes
   included); the shipped model's end-to-end shape VAE is listed too. Expression space: the
   expression VAE vs PCA on 500 random facial-action mixes.
3. Pose correctives: error on held-out poses in the joint blend zones with the correctives on
   and switched off, and (when --no-correctives-weights is given) a model trained without them.
4. Forward-pass time (ms per call, CPU, 1 thread unless --threads, float32) at batch 1 and 64,
   ours with and without correctives vs Anny's own forward pass at the same resolution (its
   default skinning, dual quaternions and torch LBS), timed interleaved round by round (medians
   and median per-round ratios; bench/body_speed.py, which also runs alone), and model size on disk.
5. Summary: one table of the headline figures per resolution (what the model card and README
   quote); --summary-only prints just this table.
6. Geometric quality on the standard pose set (humotion.body.quality.POSE_SET: real CMU frames
   with the arms down, up and out, a squat, sitting, reaching across, looking over the shoulder):
   per pose and region (shoulders, armpits, neck, elbows, wrists, hips, knees) the 99th
   percentile and worst vertex error against Anny's dual-quaternion mesh in the same pose (Anny
   installed) and the edge stretch against the rest mesh; the mapping's clavicle rotations; the
   lowest vertex over the 02_01 walk with the floor from the first frame's ankles and from foot
   contacts. --pose-set runs only this (no data folder needed; about a minute), --before adds the
   collars aimed as before issue 23, --pictures DIR renders the pose set (front and side).

The whole run takes about 9 CPU-minutes on one thread (14 minutes of wall time on the shared
2-core machine under load); the shape curve's six VAEs are about 5 of them (--reuse-curve takes
the curve from an earlier --json file instead, --skip-curve leaves it out).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import click
import numpy as np
import torch

from humotion.body import files, quality
from humotion.body.evaluation import load_meshes, summarise, vertex_errors
from humotion.body.model import BodyModel, load_body_model, shipped_weights
from humotion.body.skinning import GAP_JOINTS
from humotion.body.train import random_activations
from humotion.body.vae import VAE, kl_divergence
from humotion.training import DEFAULT_DATA

sys.path.insert(0, str(Path(__file__).resolve().parent))
import body_speed  # noqa: E402  (bench/body_speed.py)

SPLITS = ("test_shapes", "test_poses", "test_both")
ZONES = tuple(GAP_JOINTS)


def table(header: list[str], rows: list[list]) -> str:
    fmt = lambda x: f"{x:.2f}" if isinstance(x, float) else str(x)  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(x) for x in row) + " |" for row in rows]
    return "\n".join(lines)


# -- 1. held-out errors ----------------------------------------------------------------------------

def region_errors(bodies: dict[str, BodyModel], data: str, fit_iterations: int) -> list[dict]:
    """Rows of table 1; the last rows per resolution pose each subject's true rest mesh instead of
    the decoded one (what is left: joints, skinning, correctives, expression)."""
    results = []
    for resolution, body in bodies.items():
        for split, rest in [(s, "encoded") for s in SPLITS] + [("test_poses", "true")]:
            meshes = load_meshes(data, resolution, split)
            for pose in ("given", "fitted"):
                errors = vertex_errors(body, meshes, fit_pose=pose == "fitted", iterations=fit_iterations, rest=rest)
                label = split if rest == "encoded" else f"{split}, true rest mesh"
                results.append({"resolution": resolution, "split": label, "pose": pose, "meshes": len(errors),
                                **summarise(errors, body, meshes)})
    return results


# -- 2. latent spaces ------------------------------------------------------------------------------

def pca_errors(train: torch.Tensor, test: torch.Tensor, sizes) -> dict[int, float]:
    """Held-out mean vertex error (mm) of PCA bases of the training rows (N, V, 3)."""
    mean = train.mean(0)
    X, Y = (train - mean).flatten(1).double(), (test - mean).flatten(1).double()
    _, _, vh = torch.linalg.svd(X, full_matrices=False)
    out = {}
    for k in sizes:
        basis = vh[:k]
        rebuilt = (Y @ basis.T) @ basis
        out[k] = float((rebuilt - Y).unflatten(-1, (-1, 3)).norm(dim=-1).mean() * 1000)
    return out


def output_basis(body: BodyModel, train: torch.Tensor) -> torch.Tensor:
    """The PCA start of a shape VAE's output layer for rest meshes (N, V, 3) (VAE.init_output_basis,
    the same for every latent size: computed once for the curve)."""
    c = body.config
    vae = VAE(3 * c.shape_points, 3 * c.num_vertices, 1, 1, c.shape_basis)
    vae.init_output_basis(((train - body.template) / body.shape_scale).flatten(1))
    return vae.output.weight.detach().clone()


def train_shape_vae(body: BodyModel, train: torch.Tensor, latent: int, steps: int, seed: int = 0,
                    kl_weight: float = 0.01, basis: torch.Tensor | None = None) -> VAE:
    """A standalone shape VAE with the body model's architecture, input points and start (PCA
    output layer; `basis`: output_basis(body, train), when already computed), trained on rest
    meshes (N, V, 3) alone."""
    c = body.config
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    vae = VAE(3 * c.shape_points, 3 * c.num_vertices, latent, c.shape_hidden, c.shape_basis)
    scale = body.shape_scale
    centred = (train - body.template) / scale
    with torch.no_grad():
        vae.output.weight.copy_(output_basis(body, train) if basis is None else basis)
        vae.output.bias.zero_()
    inputs = centred[:, body.shape_points].flatten(1)
    optimizer = torch.optim.Adam(vae.parameters(), lr=1e-3)
    for step in range(steps):
        for group in optimizer.param_groups:
            group["lr"] = 1e-3 * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * step / steps)))
        rows = torch.randint(0, len(train), (32,), generator=generator)
        mu, logvar = vae.encode(inputs[rows])
        decoded = vae.decode(VAE.sample_posterior(mu, logvar, generator)).unflatten(-1, (-1, 3))
        error = ((decoded - centred[rows]).norm(dim=-1) * scale * 1000).mean()
        loss = error + kl_weight * kl_divergence(mu, logvar).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return vae.eval()


@torch.no_grad()
def vae_error(body: BodyModel, vae: VAE, test: torch.Tensor) -> float:
    centred = (test - body.template) / body.shape_scale
    mu, _ = vae.encode(centred[:, body.shape_points].flatten(1))
    decoded = vae.decode(mu).unflatten(-1, (-1, 3))
    return float(((decoded - centred).norm(dim=-1) * body.shape_scale * 1000).mean())


def shape_curve(body: BodyModel, data: str, sizes, steps: int) -> dict:
    model = files.load_model_file(data, body.config.resolution)
    shapes = files.load_shapes(data)
    held = torch.as_tensor(shapes["held_out"])
    rest = torch.as_tensor(model["rest_vertices"])
    train = [rest[~held]]
    extra = files.load_rest_shapes(data, body.config.resolution)
    if extra is not None:
        train.append(torch.as_tensor(extra["rest_vertices"]))
    train, test = torch.cat(train), rest[held]
    pca = pca_errors(train, test, sorted(set(sizes) | {96, 128}))
    vae = {}
    basis = output_basis(body, train)
    for k in sizes:
        start = time.perf_counter()
        vae[k] = vae_error(body, train_shape_vae(body, train, k, steps, basis=basis), test)
        print(f"  shape VAE {k:3d}: {vae[k]:.2f} mm held-out ({time.perf_counter() - start:.0f} s)", file=sys.stderr,
              flush=True)
    with torch.no_grad():
        mu, _ = body.encode_shape(test)
        model_error = float(((body.decode_shape(mu) - test).norm(dim=-1) * 1000).mean())
    return {"train_subjects": len(train), "test_subjects": len(test), "pca": pca, "vae": vae,
            "model": {body.config.shape_latent: model_error}}


@torch.no_grad()
def expression_curve(body: BodyModel, data: str, count: int = 500) -> dict:
    model = files.load_model_file(data, body.config.resolution)
    basis = torch.as_tensor(model["expression_basis"])
    generator = torch.Generator().manual_seed(123)
    train = torch.einsum("be,evc->bvc", random_activations(4000, len(basis), generator), basis)
    test = torch.einsum("be,evc->bvc", random_activations(count, len(basis), generator), basis)
    moved = body.expression_index
    mu, _ = body.encode_expression(test)
    vae = float(((body.decode_expression(mu) - test)[:, moved].norm(dim=-1) * 1000).mean())
    X, Y = train[:, moved].flatten(1).double(), test[:, moved].flatten(1).double()
    _, _, vh = torch.linalg.svd(X, full_matrices=False)  # uncentred: zero offsets stay zero
    pca = {}
    for k in (5, 10, 20, 30, 40, 52):
        b = vh[:k]
        pca[k] = float((((Y @ b.T) @ b) - Y).unflatten(-1, (-1, 3)).norm(dim=-1).mean() * 1000)
    return {"vae": {body.config.expression_latent: vae}, "pca": pca,
            "note": "mean over the vertices expressions move; offsets are linear in 52 actions, so PCA-52 is exact"}


# -- 3. correctives ---------------------------------------------------------------------------------

def corrective_table(body: BodyModel, data: str, ablation: BodyModel | None, fit_iterations: int,
                     regions: list[dict] | None = None) -> list[dict]:
    """Rows of table 3; the rows with correctives are taken from table 1's test_poses rows
    (`regions`) when given (the same computation)."""
    meshes = load_meshes(data, body.config.resolution, "test_poses")
    done = {r["pose"]: r for r in regions or () if r["resolution"] == body.config.resolution
            and r["split"] == "test_poses"}
    rows = []
    for pose in ("given", "fitted"):
        fit = pose == "fitted"
        for name, model, on in (("correctives", body, True), ("switched off", body, False),
                                ("trained without", ablation, True)):
            if model is None:
                continue
            if name == "correctives" and pose in done:
                keep = ("all", "body", "face", "hands", *ZONES)
                rows.append({"resolution": body.config.resolution, "pose": pose, "model": name,
                             **{k: done[pose][k] for k in keep}})
                continue
            errors = vertex_errors(model, meshes, fit_pose=fit, correctives=on, iterations=fit_iterations)
            rows.append({"resolution": body.config.resolution, "pose": pose, "model": name,
                         **summarise(errors, model, meshes)})
    return rows


# -- 4. speed and size: bench/body_speed.py ---------------------------------------------------------

# -- 5. summary -----------------------------------------------------------------------------------------

def model_shape_error(body: BodyModel, data: str) -> float:
    """The model's own (end-to-end) shape VAE on the held-out subjects' rest meshes, mm."""
    model = files.load_model_file(data, body.config.resolution)
    held = torch.as_tensor(files.load_shapes(data)["held_out"])
    test = torch.as_tensor(model["rest_vertices"])[held]
    with torch.no_grad():
        mu, _ = body.encode_shape(test)
        return float(((body.decode_shape(mu) - test).norm(dim=-1) * 1000).mean())


def summary_rows(results: dict, bodies: dict[str, BodyModel], data: str) -> tuple[list[str], list[list]]:
    """One table: rows = headline figures, columns = resolutions."""
    resolutions = list(bodies)
    rows = [["vertices / joints", *[f"{b.num_vertices:,} / {b.num_joints}" for b in bodies.values()]]]
    regions = {(r["resolution"], r["split"], r["pose"]): r for r in results["regions"]}
    for split in SPLITS:
        for pose in ("given", "fitted"):
            cells = []
            for res in resolutions:
                r = regions.get((res, split, pose))
                cells.append("-" if r is None else " / ".join(f"{r[k]:.2f}" for k in ("all", "body", "face", "hands")))
            rows.append([f"{split}, {pose} pose: all / body / face / hands (mm)", *cells])
    corr = {(r["resolution"], r["pose"], r["model"]): r for r in results["correctives"]}
    for pose in ("given", "fitted"):
        cells = []
        for res in resolutions:
            on, off = corr.get((res, pose, "correctives")), corr.get((res, pose, "switched off"))
            cells.append("-" if on is None or off is None else
                         " / ".join(f"{off[z]:.2f} -> {on[z]:.2f}" for z in ("shoulders", "elbows", "hips", "knees")))
        rows.append([f"correctives off -> on, test_poses, {pose} pose: shoulders / elbows / hips / knees (mm)", *cells])
    for pose in ("given", "fitted"):
        cells = []
        for res in resolutions:
            r = corr.get((res, pose, "trained without"))
            cells.append("-" if r is None else
                         " / ".join(f"{r[z]:.2f}" for z in ("all", "shoulders", "elbows", "hips", "knees")))
        if any(c != "-" for c in cells):
            rows.append([f"model trained without correctives, test_poses, {pose} pose: all / shoulders / elbows / hips "
                         "/ knees (mm)", *cells])
    curve = results.get("shape_curve")
    cells = []
    for res, body in bodies.items():
        own = f"model's VAE-{body.config.shape_latent} {model_shape_error(body, data):.2f}"
        if curve is not None and res == "low":
            own += "; alone VAE vs PCA: " + ", ".join(f"{k}: {curve['vae'][k]:.2f} vs {curve['pca'][k]:.2f}"
                                                      for k in sorted(curve["vae"]) if k in curve["pca"])
        cells.append(own)
    rows.append(["shape space, held-out subjects' rest meshes (mm)", *cells])
    speed = results.get("speed", {})
    for batch in (1, 64):
        cells = []
        for res in resolutions:
            s = speed.get(res, {}).get("batches", {}).get(batch)
            if s is None:
                cells.append("-")
                continue
            cell = f"ours {s['ours']['median_ms']:.1f} ({s['ours, no correctives']['median_ms']:.1f} without correctives)"
            for name in ("Anny default", "Anny DQS", "Anny LBS"):
                if name in s:
                    cell += f"; {name} {s[name]['median_ms']:.1f} ({s[name]['ratio_to_ours']:.1f}x)"
            cells.append(cell)
        rows.append([f"forward pass, batch {batch} (ms, 1 thread, float32; Anny / ours)", *cells])
    size = results.get("size", {})
    rows.append(["weights on disk (MB; float16 storage / float32)",
                 *[f"{size[r]['megabytes']:.1f} / {size[r]['float32_megabytes']:.1f}" if r in size else "-"
                   for r in resolutions]])
    if any("anny_tensors_megabytes" in size.get(r, {}) for r in resolutions):
        rows.append(["Anny's model tensors at that resolution (MB, float64)",
                     *[str(size.get(r, {}).get("anny_tensors_megabytes", "-")) for r in resolutions]])
    return ["", *resolutions], rows


# -- 6. geometric quality on the standard pose set -------------------------------------------------

POSE_BUILDS = ((1.85, 80.0), (1.60, 55.0))
"""Bodies of the pose-set figures without Anny (height m, weight kg)."""

ANNY_PHENOTYPES = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5)
"""The Anny body of the comparison against Anny's own dual-quaternion meshes (its default)."""

WALK = ("cmu_mocgui_s02/02_01.amc", "cmu_mocgui_s02/02.asf")
"""The take of the feet check (the walk of issue 23), resampled to 30 fps."""


def stretch_rows(body: BodyModel, rest, rest_joints, posed: dict, reference: dict | None = None) -> list[dict]:
    """Rows per pose and region of quality.REGION_JOINTS: edge stretch (worst, p99) of posed
    meshes {name: (V, 3)} against rest (V, 3); with reference {name: (V, 3)} Anny's meshes, the
    vertex error (mm, worst, p99) against them and their own edge stretch."""
    edges = quality.mesh_edges(body.faces.numpy())
    masks = quality.region_masks(rest, rest_joints, body.joint_names)
    rows = []
    for name, vertices in posed.items():
        stretch = quality.edge_stretch(vertices, rest, edges)
        ref_stretch = None if reference is None else quality.edge_stretch(reference[name], rest, edges)
        errors = None if reference is None else np.linalg.norm(vertices - reference[name], axis=-1) * 1000
        for region, mask in masks.items():
            row = {"pose": name, "region": region, **{f"stretch_{k}": v for k, v in
                                                     quality.region_stretch(stretch, edges, mask).items()}}
            if reference is not None:
                row.update({f"error_{k}": v for k, v in quality.region_errors(errors, mask).items()})
                row.update({f"anny_stretch_{k}": v for k, v in quality.region_stretch(ref_stretch, edges, mask).items()})
            rows.append(row)
    return rows


def pose_set_quality(bodies: dict[str, BodyModel], mocap: Path, held, anny_cache: dict) -> dict:
    """The pose set's figures per resolution: against Anny's meshes (when Anny is installed:
    Anny's rest mesh posed by the model and by Anny's dual quaternions, the same rig rotations)
    and edge stretch alone on bodies of POSE_BUILDS."""
    from humotion.body.export import rest_body
    from humotion.body.posing import canonical_to_rig

    poses = quality.pose_set(mocap)
    canonical = torch.stack(list(poses.values()))
    out = {}
    for resolution, body in bodies.items():
        results = {"builds": {}, "anny": None}
        for height, weight in POSE_BUILDS:
            rest = rest_body(body, body.shape_from_measurements(height, weight))
            local = canonical_to_rig(canonical.double(), rest.vertices.double(), rest.joints.double(), body.joint_names,
                                     body.parents, held=held)
            with torch.no_grad():
                posed = body(rest_vertices=rest.vertices[None], pose=torch.as_tensor(local, dtype=torch.float32)).vertices
            results["builds"][f"{height:.2f} m, {weight:.0f} kg"] = stretch_rows(
                body, rest.vertices.double().numpy(), rest.joints.double().numpy(),
                dict(zip(poses, posed.double().numpy())))
        anny = anny_cache.get(resolution)
        if anny is not None:
            phenotypes = np.array([ANNY_PHENOTYPES])
            shapes = anny.rest(phenotypes)
            rest_v, rest_j = shapes.vertices[0], shapes.joints[0]
            local = canonical_to_rig(canonical.double(), torch.from_numpy(rest_v), torch.from_numpy(rest_j),
                                     anny.joint_names, anny.parents, held=held).numpy()
            reference = anny.pose(phenotypes, None, local, np.zeros((len(local), 3)))
            with torch.no_grad():
                posed = body(rest_vertices=torch.as_tensor(rest_v, dtype=torch.float32)[None],
                             pose=torch.as_tensor(local, dtype=torch.float32)).vertices.double().numpy()
            results["anny"] = stretch_rows(body, rest_v, rest_j, dict(zip(poses, posed)), dict(zip(poses, reference)))
            results["anny_meshes"] = (posed, reference)
        results["meshes"] = posed
        out[resolution] = results
    return out


def feet_on_floor_figures(body: BodyModel, mocap: Path) -> dict:
    """Lowest vertex of the 02_01 walk on a 1.85 m, 80 kg body at 30 fps, per frame, with and
    without the per-frame floor offsets (humotion.body.floor); and on the frames where a foot is
    in contact, the lowest vertex of the feet in contact."""
    from humotion.body.export import feet_on_floor, pose_motion, posed_vertices, rest_body
    from humotion.body.floor import lowest_foot_points
    from humotion.io import load_motion

    motion = load_motion(mocap / WALK[0], asf=mocap / WALK[1]).resample(30.0)
    rest = rest_body(body, body.shape_from_measurements(1.85, 80.0))
    out = {"frames": motion.num_frames}
    for label, floor in (("first frame's ankles (before)", False), ("foot contacts (now)", True)):
        rotations, root = pose_motion(rest, motion, floor=floor)
        lowest = posed_vertices(rest, rotations, root, progress=False)[..., 1].amin(1).numpy()
        _, contacts = feet_on_floor(rest, rotations, root, motion.fps)
        points = lowest_foot_points(body, rest.vertices, rest.joints, rotations, root - rest.joints[0]).numpy()
        in_contact = np.where(contacts, points[:, :, 0, 1], np.inf).min(1)
        in_contact = in_contact[np.isfinite(in_contact)]
        out[label] = {"lowest_min_cm": float(lowest.min() * 100), "lowest_max_cm": float(lowest.max() * 100),
                      "contact_frames": int(len(in_contact)),
                      "contact_abs_max_cm": float(np.abs(in_contact).max() * 100) if len(in_contact) else None}
    return out


def print_pose_set(results: dict, held_label: str) -> None:
    for resolution, r in results.items():
        if r["anny"] is not None:
            click.echo(f"\n### {resolution}: against Anny's dual-quaternion meshes ({held_label}; Anny's default "
                       "body posed by the model and by Anny, same rig rotations)\n")
            click.echo(table(["pose", "region", "error p99 (mm)", "error worst (mm)", "stretch p99", "stretch worst",
                              "Anny's stretch p99", "Anny's stretch worst"],
                             [[x["pose"], x["region"], x["error_p99"], x["error_worst"], x["stretch_p99"],
                               x["stretch_worst"], x["anny_stretch_p99"], x["anny_stretch_worst"]] for x in r["anny"]]))
        for build, rows in r["builds"].items():
            click.echo(f"\n### {resolution}: edge stretch, body of {build} ({held_label})\n")
            regions = list(dict.fromkeys(x["region"] for x in rows))
            poses = list(dict.fromkeys(x["pose"] for x in rows))
            cell = {(x["pose"], x["region"]): f"{x['stretch_p99']:.2f} / {x['stretch_worst']:.2f}" for x in rows}
            click.echo(table(["pose (p99 / worst)", *regions], [[p, *[cell[p, g] for g in regions]] for p in poses]))


def collar_figures(body: BodyModel, mocap: Path) -> dict:
    """The mapping's collars on the arms-down pose: the canonical collars' rotation and the rig
    clavicles' local rotation (degrees) with the collars aimed (before) and held at rest (now)."""
    from humotion import rotations as rot
    from humotion.body.posing import canonical_to_rig
    from humotion.canonical import JOINTS

    pose = quality.pose_set(mocap, quality.POSE_SET[:1])["arms_down"]
    out = {f"canonical {side} collar": float(np.degrees(rot.convert(pose[JOINTS.index(f"{side}_collar")].double(),
                                                                     "quat", "rotvec").norm()))
           for side in ("left", "right")}
    with torch.no_grad():
        rest, joints = body.decode_shape_and_joints(body.shape_from_measurements(1.85, 80.0))
    for label, held in (("aimed (before)", ()), ("held at rest (now)", None)):
        kwargs = {} if held is None else {"held": held}
        local = canonical_to_rig(pose[None].double(), rest[0].double(), joints[0].double(), body.joint_names,
                                 body.parents, **kwargs)[0]
        for side in ("L", "R"):
            angle = rot.convert(local[body.joint_names.index(f"clavicle.{side}")], "matrix", "rotvec")
            out[f"clavicle.{side}, collars {label}"] = float(np.degrees(angle.norm()))
    return out


def run_pose_set(bodies: dict[str, BodyModel], mocap: Path, before: bool, pictures: str | None) -> dict:
    """Section 6: the pose set (with the collars held at rest, and aimed as before issue 23 when
    `before`), the collars' rotations, the feet over the walk, and the pictures."""
    from humotion.body.anny_source import anny_version
    from humotion.body.posing import HELD_AT_REST

    anny_cache = {}
    if anny_version():
        from humotion.body.anny_source import TOPOLOGIES, AnnyBody
        anny_cache = {r: AnnyBody(TOPOLOGIES[r]) for r in bodies}
    else:
        click.echo("(Anny is not installed: no comparison against its meshes; pip install 'anny==0.6.2')")
    results = {}
    click.echo("\n## Standard pose set (humotion.body.quality.POSE_SET): edge stretch and errors per region\n")
    for pose in quality.POSE_SET:
        click.echo(f"- {pose.name}: {pose.clip} frame {pose.frame} (120 Hz): {pose.what}")
    runs = [("collars held at rest (now)", HELD_AT_REST, "now")]
    if before:
        runs.append(("collars aimed (before)", (), "before"))
    for label, held, _ in runs:
        results[label] = pose_set_quality(bodies, mocap, held, anny_cache)
        print_pose_set(results[label], label)
    first = next(iter(bodies.values()))
    results["collars"] = collar_figures(first, mocap)
    click.echo("\n### The mapping's collars on arms_down (degrees)\n")
    click.echo(table(["rotation", "degrees"], [[k, v] for k, v in results["collars"].items()]))
    click.echo("\n### Feet over the 02_01 walk (30 fps, 1.85 m, 80 kg; lowest vertex of the body, cm)\n")
    rows = []
    for resolution, body in bodies.items():
        feet = feet_on_floor_figures(body, mocap)
        results[f"feet {resolution}"] = feet
        for label in ("first frame's ankles (before)", "foot contacts (now)"):
            f = feet[label]
            rows.append([resolution, label, f["lowest_min_cm"], f["lowest_max_cm"], f["contact_frames"],
                         "-" if f["contact_abs_max_cm"] is None else f["contact_abs_max_cm"]])
    click.echo(table(["resolution", "floor from", "lowest min", "lowest max", "contact frames",
                      "worst height of a contact foot"], rows))
    if pictures:
        folder = Path(pictures)
        folder.mkdir(parents=True, exist_ok=True)
        for label, _, tag in runs:
            for resolution, r in results[label].items():
                body = bodies[resolution]
                path = folder / f"pose_set_{resolution}_{tag}.png"
                quality.render_poses(list(r["meshes"]), body.faces.numpy(), [p.name for p in quality.POSE_SET], path)
                click.echo(f"wrote {path}")
                if "anny_meshes" in r:
                    ours, reference = r["anny_meshes"]
                    path = folder / f"shoulders_{resolution}_{tag}.png"
                    quality.render_poses([reference[0], ours[0]], body.faces.numpy(),
                                         ["Anny (DQS), arms_down", "ours, arms_down"], path, size=1.8, dpi=70,
                                         top=0.5)
                    click.echo(f"wrote {path}")
    return results


# -- command line --------------------------------------------------------------------------------------

@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--data", default="runs/body_data", show_default=True, type=click.Path(file_okay=False))
@click.option("--mocap", default=str(DEFAULT_DATA), show_default=True, type=click.Path(exists=True, file_okay=False),
              help="Mocap root of the pose set (CMU takes) and the walk.")
@click.option("--pose-set", "pose_set_only", is_flag=True,
              help="Only section 6: the standard pose set's edge stretch and errors against Anny, the feet, pictures.")
@click.option("--before", is_flag=True, help="Section 6 also with the collars aimed, as before issue 23.")
@click.option("--pictures", type=click.Path(file_okay=False), help="Section 6 writes its PNG renders into this folder.")
@click.option("--low", "low_path", help="Low-resolution weights (default: the shipped ones).")
@click.option("--full", "full_path", help="Full-resolution weights (default: the shipped ones).")
@click.option("--no-correctives-weights", help="A low-resolution model trained without correctives (ablation).")
@click.option("--curve-sizes", default="2,4,8,16,32,64", show_default=True, help="Shape VAE latent sizes.")
@click.option("--curve-steps", default=3000, show_default=True, help="Adam steps per curve VAE.")
@click.option("--fit-iterations", default=20, show_default=True, help="L-BFGS iterations of the fitted rows.")
@click.option("--skip-curve", is_flag=True)
@click.option("--skip-speed", is_flag=True)
@click.option("--threads", default=1, show_default=True)
@click.option("--rounds", default=11, show_default=True, help="Interleaved timing rounds per batch size.")
@click.option("--resolution", "resolutions", type=click.Choice(["low", "full"]), multiple=True,
              help="Resolutions to evaluate (default: both).")
@click.option("--summary-only", is_flag=True, help="Print only the summary table (not the detailed ones).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Also write the results as JSON.")
@click.option("--reuse-curve", type=click.Path(exists=True, dir_okay=False),
              help="Take the shape-space curve from an earlier --json file instead of training its VAEs again.")
def main(data, mocap, pose_set_only, before, pictures, low_path, full_path, no_correctives_weights, curve_sizes,
         curve_steps, fit_iterations, skip_curve, skip_speed, threads, rounds, resolutions, summary_only, json_path,
         reuse_curve):
    """Held-out errors, latent-space curves, corrective ablation, speed and size of the body model."""
    torch.set_num_threads(threads)
    show = (lambda *args: None) if summary_only else print  # the detailed tables
    paths = {"low": Path(low_path) if low_path else shipped_weights("low"),
             "full": Path(full_path) if full_path else shipped_weights("full")}
    paths = {k: v for k, v in paths.items() if v.exists() and (not resolutions or k in resolutions)}
    if not paths:
        raise click.ClickException("no body model weights: train them (humotion train body) or pass --low / --full")
    bodies = {k: load_body_model(v) for k, v in paths.items()}
    results: dict = {"weights": {k: str(v) for k, v in paths.items()}, "threads": threads}
    started = time.perf_counter()
    if pose_set_only:
        run_pose_set(bodies, Path(mocap), before, pictures)
        click.echo(f"\n({time.perf_counter() - started:.0f} s)")
        return
    if not Path(data).is_dir():
        raise click.BadParameter(f"{data}: no such folder (make it: python -m humotion.body.command data --out {data})",
                                 param_hint="--data")

    show("\n## Held-out error (mm)\n")
    results["regions"] = region_errors(bodies, data, fit_iterations)
    show(table(["resolution", "split", "pose", "meshes", "all", "body", "face", "hands", *ZONES],
                [[r["resolution"], r["split"], r["pose"], r["meshes"], r["all"], r["body"], r["face"], r["hands"],
                  *[r[z] for z in ZONES]] for r in results["regions"]]))

    show("\n## Pose correctives on held-out poses (mm)\n")
    ablation = load_body_model(no_correctives_weights) if no_correctives_weights else None
    rows = []
    for resolution, body in bodies.items():
        rows += corrective_table(body, data, ablation if resolution == "low" else None, fit_iterations,
                                 results["regions"])
    results["correctives"] = rows
    show(table(["resolution", "pose", "model", "all", *ZONES],
                [[r["resolution"], r["pose"], r["model"], r["all"], *[r[z] for z in ZONES]] for r in rows]))

    if not skip_curve and "low" in bodies:
        if json_path:  # keep what is done so far
            Path(json_path).write_text(json.dumps(results, indent=1, default=str) + "\n")
        show("\n## Shape space: VAE vs PCA, held-out subjects' rest meshes (low resolution, mm)\n")
        sizes = [int(s) for s in curve_sizes.split(",")]
        if reuse_curve:
            curve = json.loads(Path(reuse_curve).read_text())["shape_curve"]
            curve = {**curve, **{k: {int(n): v for n, v in curve[k].items()} for k in ("pca", "vae", "model")}}
        else:
            curve = shape_curve(bodies["low"], data, sizes, curve_steps)
        results["shape_curve"] = curve
        all_sizes = sorted(set(curve["pca"]) | set(curve["vae"]) | set(curve["model"]))
        show(table(["latent size", "PCA", "VAE (alone)", "VAE (shipped model, end to end)"],
                    [[k, curve["pca"].get(k, "-"), curve["vae"].get(k, "-"), curve["model"].get(k, "-")]
                     for k in all_sizes]))
        show(f"\n{curve['train_subjects']} training subjects, {curve['test_subjects']} held-out subjects.")
        expression = expression_curve(bodies["low"], data)
        results["expression_curve"] = expression
        show("\nExpression space (mm over the moved vertices, 500 random facial-action mixes): "
              + ", ".join(f"VAE-{k} {v:.3f}" for k, v in expression["vae"].items()) + "; "
              + ", ".join(f"PCA-{k} {v:.3f}" for k, v in expression["pca"].items()))

    if not skip_speed:
        show(f"\n## Forward pass, ms per call (median of {rounds} interleaved rounds; CPU, {threads} thread(s), "
              "float32) and size\n")
        weights = {k: str(v) for k, v in paths.items()}
        results["speed"] = body_speed.speed_table(list(bodies), (1, 64), rounds, weights=weights,
                                                  log=lambda line: print(line, file=sys.stderr, flush=True))
        show(body_speed.speed_markdown(results["speed"]))
        skinning = next(iter(results["speed"].values()))["anny_skinning"]
        if skinning:
            show("\nAnny's skinning functions: " + "; ".join(f"{k} = {v}" for k, v in skinning.items())
                  + ". Ratios: median over rounds of Anny / ours (with correctives) timed in the same round.")
        results["size"] = body_speed.sizes(list(bodies), weights)
        show("")
        show(body_speed.sizes_markdown(results["size"]))

    click.echo("\n## Summary\n")
    header, rows = summary_rows(results, bodies, data)
    click.echo(table(header, rows))
    results["pose_set"] = run_pose_set(bodies, Path(mocap), before, pictures)
    click.echo(f"\n({time.perf_counter() - started:.0f} s)")

    if json_path:
        Path(json_path).write_text(json.dumps(results, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
