"""Extra neutral rest shapes for a body data folder: more subjects for the shape space.

    python -m humotion.body.command rest-shapes --data runs/body_data --count 2000

Posing and skinning every training mesh is the slow part of :mod:`humotion.body.dataset`
(~0.2 s a mesh); a subject's rest shape alone (A pose, neutral face) takes Anny ~0.1 s at full
resolution. The shape VAE, the joint regressor and the height/weight controls learn from rest
shapes, and 180 subjects are few for a 16-dimensional latent (a VAE overfits them), so this adds
`count` more subjects, drawn like the folder's (Anny's WHO-calibrated phenotype sampler, the
folder's age range) with another seed: new, independent bodies, none of them a held-out one.

Writes DATA/rest_shapes.npz: phenotypes (N, 6) + phenotype_names, age_years, height, mass, bmi,
waist_circumference, volume (N,), rest_joints (N, J, 3), rest_vertices_full (N, 13718, 3) and
rest_vertices_low (N, 1229, 3) float32 (same frame and conventions as {full,low}/model.npz), and
a manifest entry rest_shapes.json (count, seed, command, Anny version). Needs Anny.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from humotion.body.files import read_manifest, save_json, save_npz

SEED_OFFSET = 1000
"""The phenotypes are drawn with seed = the folder's seed + SEED_OFFSET (never the folder's own)."""


def make_rest_shapes(folder: str | Path, count: int = 2000, chunk: int = 100, progress: bool = True,
                     command: str = "") -> dict:
    """Write DATA/rest_shapes.npz (see the module docstring); returns its manifest entry."""
    from humotion.body import anny_source

    folder = Path(folder)
    manifest = read_manifest(folder)
    settings = manifest["settings"]
    seed = int(manifest["seed"]) + SEED_OFFSET
    start = time.perf_counter()
    bodies = {name: anny_source.AnnyBody(topology) for name, topology in manifest["topologies"].items()}
    full = bodies["full"]
    phenotypes, ages = anny_source.sample_phenotypes(full, count, seed, settings["min_age"], settings["max_age"])
    parts: dict[str, list[np.ndarray]] = {}
    bar = tqdm(total=count, desc="rest shapes", unit="shape", disable=not progress)
    for a in range(0, count, chunk):
        rests = {name: body.rest(phenotypes[a:a + chunk]) for name, body in bodies.items()}
        for name, rest in rests.items():
            if np.abs(rest.joints - rests["full"].joints).max() > 1e-4:
                raise RuntimeError(f"{name} topology's joints differ from the full one's")
            parts.setdefault(f"rest_vertices_{name}", []).append(rest.vertices.astype(np.float32))
        parts.setdefault("rest_joints", []).append(rests["full"].joints.astype(np.float32))
        measures = full.anthropometry(rests["full"].vertices)
        for key, value in measures.items():
            parts.setdefault(key, []).append(value.astype(np.float32))
        bar.update(len(rests["full"].vertices))
    bar.close()
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    save_npz(folder / "rest_shapes.npz", dict(phenotypes=phenotypes.astype(np.float32),
                                              phenotype_names=np.array(full.phenotype_names),
                                              age_years=ages.astype(np.float32), **arrays))
    entry = dict(count=count, seed=seed, command=command, anny_version=anny_source.anny_version(),
                 seconds=round(time.perf_counter() - start, 1), licence=manifest.get("licence"))
    save_json(folder / "rest_shapes.json", entry)
    return entry

