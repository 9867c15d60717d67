"""How faithfully a body's glTF file skins it: the file's joint influences against the model.

    .venv/bin/python bench/body_gltf_skin.py [--resolution low] [--frames 3000]

glTF consumers read 4 joint influences per vertex (JOINTS_0/WEIGHTS_0). For bodies of three
builds posed by held-out CMU motion (the test subjects' takes, every 10th frame at 30 fps), this
prints the vertex error (mm: max, 99th percentile, median) of the file's skinning against the
model's own vertices, pose correctives included on both sides, for:
- the model's 4 heaviest weights per vertex, renormalised;
- the 4 fitted by humotion.body.skin_export.four_joint_weights (what `humotion body` writes);
- 8 influences (`--influences 8`).

Then the standard pose set (humotion.body.quality.POSE_SET, real CMU frames: arms down, up and
out, squat, sitting, reaching across, looking over the shoulder) through the file's own skin: the
4 fitted influences with the correctives as the file's morph targets (their weights the
corrective code, as `humotion body` animates them). Per pose, the vertex error against the model
(mm, worst) and the worst edge stretch at the shoulders (tops and armpits) of the file's mesh and
of the model's, so the file keeps the model's shoulders.
"""

from __future__ import annotations

import argparse

import torch

import numpy as np

from humotion.body import quality
from humotion.body.export import rest_body
from humotion.body.model import load_body_model
from humotion.body.skin_export import four_joint_weights
from humotion.body.skinning import linear_blend_skinning
from humotion.canonical import to_canonical
from humotion.io.gltf import skin_influences
from humotion.sparse.evaluation import test_sets
from humotion.training import DEFAULT_DATA

BUILDS = ((1.85, 80.0), (1.55, 50.0), (1.75, 110.0))   # height m, weight kg


def held_out_poses(frames: int) -> torch.Tensor:
    """(F, 22, 4) canonical rotations: every 10th frame (30 fps) of the CMU test subjects' takes."""
    poses = []
    for clip in test_sets(DEFAULT_DATA)["CMU test"]:
        poses.append(to_canonical(clip.load()).resample(30.0).rotations[::10])
        if sum(len(p) for p in poses) >= frames:
            break
    return torch.cat(poses)[:frames]


def as_in_file(weights: torch.Tensor, count: int) -> torch.Tensor:
    """(V, J) weights as a glTF file holds them: `count` joints per vertex, float32, renormalised."""
    joints, kept = skin_influences(weights.numpy(), count)
    return torch.zeros(weights.shape, dtype=torch.float64).scatter_add_(
        1, torch.as_tensor(joints), torch.as_tensor(kept, dtype=torch.float64))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", default="low", choices=("low", "full"))
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--pose-set", action="store_true", help="only the standard pose set")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model = load_body_model(args.resolution)
    if args.pose_set:
        torch.set_num_threads(1)
        pose_set_through_the_file(model)
        return 0
    canonical = held_out_poses(args.frames)
    weights = model.skinning_weights().detach()
    print(f"{args.resolution} ({model.num_vertices} vertices), {len(canonical)} held-out CMU frames; "
          "vertex error of the file's skinning against the model, mm")
    for height, weight in BUILDS:
        body = rest_body(model, model.shape_from_measurements(height, weight))
        poses = model.pose_from_canonical(canonical, body.shape)
        methods = {"4 heaviest": as_in_file(weights, 4),
                   "4 fitted (shipped)": as_in_file(four_joint_weights(weights, body.vertices, body.joints, model.parents,
                                                                        model.limits), 4),
                   "8 influences": as_in_file(weights, 8)}
        errors = {name: [] for name in methods}
        with torch.no_grad():
            for start in range(0, len(poses), 100):
                pose = poses[start:start + 100]
                out = model(rest_vertices=body.vertices[None], pose=pose)
                surface = (out.rest_vertices + model.corrective_offsets(pose, out.rest_vertices)).double()
                A, t = out.world_rotations.double(), out.translations.double()
                for name, file_weights in methods.items():
                    skinned = linear_blend_skinning(surface, file_weights, A, t)
                    errors[name].append(((skinned - out.vertices.double()).norm(dim=-1) * 1000).flatten())
        print(f"  body {height:.2f} m, {weight:.0f} kg")
        for name, parts in errors.items():
            e = torch.cat(parts)
            sample = e[::max(1, len(e) // 5_000_000)]
            print(f"    {name:20s} max {e.max():6.2f}   p99 {sample.quantile(0.99):5.2f}   median {e.median():.4f}")
    pose_set_through_the_file(model)
    return 0


def pose_set_through_the_file(model) -> None:
    """The pose set skinned as the glTF file skins it (4 fitted influences, correctives as morph
    targets with the file's weights) against the model, for each build."""
    poses = quality.pose_set(DEFAULT_DATA)
    canonical = torch.stack(list(poses.values()))
    edges = quality.mesh_edges(model.faces.numpy())
    print(f"\nstandard pose set through the file's skin ({model.config.resolution}): error against the model (mm, "
          "worst); worst edge stretch at the shoulders / armpits, file vs model")
    for height, weight in BUILDS:
        body = rest_body(model, model.shape_from_measurements(height, weight))
        rest = body.vertices.double().numpy()
        masks = quality.region_masks(rest, body.joints.numpy(), model.joint_names)
        rotations = model.pose_from_canonical(canonical, body.shape)
        skin = as_in_file(four_joint_weights(model.skinning_weights().detach(), body.vertices, body.joints,
                                             model.parents, model.limits), 4)
        with torch.no_grad():
            out = model(rest_vertices=body.vertices[None], pose=rotations)
            targets = model.correctives.targets() * model.corrective_scale(body.vertices[None])     # (K, V, 3)
            morphed = body.vertices[None] + torch.einsum("pk,kvc->pvc", model.correctives.hidden(rotations), targets)
            file_vertices = linear_blend_skinning(morphed.double(), skin, out.world_rotations.double(),
                                                  out.translations.double()).numpy()
        ours = out.vertices.double().numpy()
        file_stretch, model_stretch = (quality.edge_stretch(v, rest, edges) for v in (file_vertices, ours))
        print(f"  body {height:.2f} m, {weight:.0f} kg")
        for i, name in enumerate(poses):
            error = np.linalg.norm(file_vertices[i] - ours[i], axis=-1).max() * 1000
            cells = [f"{quality.region_stretch(s[i], edges, masks[region])['worst']:.2f}"
                     for region in ("shoulders", "armpits") for s in (file_stretch, model_stretch)]
            print(f"    {name:20s} error {error:5.2f}   shoulders {cells[0]} / {cells[1]}   armpits {cells[2]} / {cells[3]}")


if __name__ == "__main__":
    raise SystemExit(main())
