"""Forward-pass speed of the learned body model vs Anny's own forward pass, and sizes on disk.

    python bench/body_speed.py                      # shipped weights, both resolutions, batch 1 and 64
    python bench/body_speed.py --rounds 30 --json runs/body/speed.json
    python bench/body_speed.py --resolution full --batches 1,16,64
    python bench/body_speed.py --float64            # also Anny as built (float64; timed in its own
                                                    # interleaved group with ours), for reference

Like with like, on one CPU thread (torch.set_num_threads(1)), float32, no gradients:

- ours: shape latent (B, 16) + expression latent (B, 20) + pose as rotation matrices (B, 76, 3, 3)
  + root translation (B, 3) -> posed vertices, with the pose correctives and without them.
- Anny 0.6.2 at the same resolution (full: topology "anny", 13,718 vertices; low:
  "notoes_collapse10pc", 1,229 vertices, the topology the low model was trained on), the same
  76-joint rig ("anny-notoes") and all 52 facial actions, cast to float32 (Anny builds float64):
  phenotypes (B, 6) + facial actions (B, 52) + local pose transforms (B, 76, 4, 4) -> posed
  vertices, with its default skinning (warp LBS when NVIDIA Warp is installed, as here; torch LBS
  otherwise), with dual-quaternion skinning (how the training meshes were posed), and with its
  dense torch LBS.

B different bodies in B different poses per call. The machine is shared and noisy, so the
variants' timings are interleaved: every round times each variant once (one call, or a block of
calls lasting at least 20 ms, after one untimed call that takes the page faults another model's
freed memory leaves behind; see `interleaved`), in an order rotated from round to round, after a
warm-up. Ours and Anny's default (Warp) kernel form one such group; Anny's DQS and torch LBS are
interleaved with ours in a second group (see ANNY_GROUPS). Reported: the median over rounds (ms
per call; ours from the first group), per Anny variant the median of the per-round ratios
Anny / ours (with correctives): "x times faster", and the median page faults per timed call.

Sizes: our weights files as shipped (float16 storage of the big matrices) and in float32, and
Anny's model data for reference (its tensors in memory as built, float64; its installed data folder).
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import click
import torch

from humotion.body.model import BodyModel, load_body_model, save_body_model, shipped_weights

OURS = (("ours", True), ("ours, no correctives", False))
ANNY = (("Anny default", None), ("Anny DQS", "dqs"), ("Anny LBS", "lbs"))
ANNY_GROUPS = ((("Anny default", None),), (("Anny DQS", "dqs"), ("Anny LBS", "lbs")))
"""Anny's variants in the groups they are interleaved with ours in. DQS and torch LBS allocate
hundreds of MB per call at batch 64, which glibc hands back to the system afterwards, so the
call after them pays page faults for all its buffers (ours, in one diagnostic: about 5,000
faults and 10 ms more at full resolution, batch 64): they are timed apart from the default (Warp)
kernel (and every timed block now starts with an untimed call as well)."""
ANNY_FLOAT64 = (("Anny default, float64", None),)
"""Anny as it is built (float64, default skinning): --float64 adds it, for reference only."""


def random_rotations(batch: int, joints: int, generator: torch.Generator, scale: float = 0.5) -> torch.Tensor:
    """(batch, joints, 3, 3) float32 rotations of random rotation vectors (about `scale` rad)."""
    from humotion import rotations as rot

    rotvec = scale * torch.randn(batch, joints, 3, generator=generator, dtype=torch.float64)
    return rot.convert(rotvec, "rotvec", "matrix").float()


def our_calls(body: BodyModel, batch: int, seed: int = 0) -> dict:
    """{variant name: zero-argument forward pass} of our model at a batch size."""
    generator = torch.Generator().manual_seed(seed)
    shape = body.sample_shapes(batch, generator)
    expression = body.sample_expressions(batch, generator)
    pose = random_rotations(batch, body.num_joints, generator)
    translation = 0.1 * torch.randn(batch, 3, generator=generator)
    calls = {}
    for name, on in OURS:
        def call(on=on):
            return body(shape=shape, expression=expression, pose=pose, translation=translation, correctives=on).vertices
        calls[name] = call
    return calls


def build_anny(topology: str, skinning: str | None, cache_dir: str | None = None, dtype=torch.float32):
    """Anny's model at a topology on the shared rig with all facial actions, no gradients, in
    dtype (Anny builds float64)."""
    from humotion.body.anny_source import DEFAULT_RIG, _import_anny

    anny = _import_anny(cache_dir)
    model = anny.Anny(rig=DEFAULT_RIG, topology=topology, facial_actions="all", skinning_method=skinning)
    model.requires_grad_(False)
    model = model.to(dtype)
    model.set_skinning_method(skinning)  # rebuild the dense LBS weights (a non-persistent buffer) in dtype
    return model


def skinning_name(model) -> str:
    """Which skinning an Anny model actually runs."""
    fn = model._skinning_method
    return f"{fn.__module__.rsplit('.', 1)[-1]}.{fn.__name__}"


def anny_calls(models: dict, batch: int, seed: int = 0) -> dict:
    """{variant name: zero-argument forward pass} of Anny's models at a batch size (the same
    inputs for every variant: phenotypes, sparse facial-action mixes, random local rotations)."""
    calls = {}
    for name, model in models.items():
        generator = torch.Generator().manual_seed(seed + 1)
        J, A = len(model.bone_labels), len(model.facial_action_labels)
        pheno = torch.rand(batch, len(model.phenotype_labels), generator=generator)
        actions = torch.rand(batch, A, generator=generator) * (torch.rand(batch, A, generator=generator) < 0.1)
        pose = torch.eye(4).repeat(batch, J, 1, 1)
        pose[..., :3, :3] = random_rotations(batch, J, generator)
        pose[:, 0, :3, 3] = 0.1 * torch.randn(batch, 3, generator=generator)
        pose, pheno, actions = (x.to(model.dtype) for x in (pose, pheno, actions))

        def call(model=model, pose=pose, pheno=pheno, actions=actions):
            return model(pose_parameters=pose, phenotype_kwargs=pheno, facial_actions=actions)["vertices"]
        calls[name] = call
    return calls


def page_faults() -> int:
    """Minor page faults of this process so far (first touches of memory the system handed over)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def interleaved(calls: dict, rounds: int, warmup: int = 2, min_block_ms: float = 20.0) -> dict[str, dict[str, list]]:
    """{name: {"ms": [ms per call, one per round], "faults": [page faults per call, one per
    round]}}: each round times every call once (a block of calls lasting at least min_block_ms),
    in an order rotated by one from round to round. Each block starts with one untimed call: glibc
    returns a large freed heap to the system, so the first call after another model's faults its
    buffers back in (thousands of page faults at full resolution, batch 64), which would charge
    each model for the other's allocations rather than time its own steady state."""
    names = list(calls)
    block = {}
    for name in names:
        for _ in range(warmup):
            calls[name]()
        start = time.perf_counter()
        calls[name]()
        once = (time.perf_counter() - start) * 1000
        block[name] = max(1, min(50, int(min_block_ms / max(once, 1e-3))))
    times = {name: {"ms": [], "faults": []} for name in names}
    for r in range(rounds):
        for name in names[r % len(names):] + names[:r % len(names)]:
            fn, n = calls[name], block[name]
            fn()
            faults, start = page_faults(), time.perf_counter()
            for _ in range(n):
                fn()
            times[name]["ms"].append((time.perf_counter() - start) * 1000 / n)
            times[name]["faults"].append((page_faults() - faults) / n)
    return times


def summarise_times(times: dict[str, dict[str, list]], reference: str = "ours") -> dict:
    """Medians (ms), quartiles, median page faults per call, and median per-round ratios to the
    reference variant."""
    out = {}
    for name, timed in times.items():
        t = timed["ms"]
        q = statistics.quantiles(t, n=4) if len(t) > 1 else [t[0]] * 3
        ratios = [a / b for a, b in zip(t, times[reference]["ms"])]
        out[name] = {"median_ms": statistics.median(t), "q1_ms": q[0], "q3_ms": q[2], "rounds": len(t),
                     "ratio_to_ours": statistics.median(ratios), "page_faults": statistics.median(timed["faults"])}
    return out


@torch.no_grad()
def speed_table(resolutions, batches, rounds: int, anny_variants=ANNY, cache_dir: str | None = None,
                weights: dict | None = None, log=print, float64: bool = False) -> dict:
    """{resolution: {"vertices", "anny_topology", "anny_skinning": {...}, "batches": {batch: summary}}}."""
    from humotion.body.anny_source import TOPOLOGIES

    weights = weights or {}
    results = {}
    for resolution in resolutions:
        body = load_body_model(weights.get(resolution, resolution))
        try:
            models = {name: build_anny(TOPOLOGIES[resolution], skinning, cache_dir)
                      for name, skinning in anny_variants}
            # timed in a group of its own with ours: Warp rebuilds its skinning module whenever the
            # dtype changes, which would charge float32 and float64 Anny alike if they alternated
            models64 = {name: build_anny(TOPOLOGIES[resolution], skinning, cache_dir, torch.float64)
                        for name, skinning in ANNY_FLOAT64} if float64 else {}
        except ImportError:
            models, models64 = {}, {}
            log("  Anny is not installed: timing ours only")
        for model in (models | models64).values():
            if model.template_vertices.shape[0] != body.num_vertices or len(model.bone_labels) != body.num_joints:
                raise RuntimeError(f"Anny's {TOPOLOGIES[resolution]} has {model.template_vertices.shape[0]} "
                                   f"vertices / {len(model.bone_labels)} joints, ours {body.num_vertices} / "
                                   f"{body.num_joints}")
        entry = {"vertices": body.num_vertices, "joints": body.num_joints, "anny_topology": TOPOLOGIES[resolution],
                 "anny_skinning": {name: skinning_name(m) for name, m in (models | models64).items()}, "batches": {}}
        groups = [{name: models[name] for name, _ in group if name in models} for group in ANNY_GROUPS]
        groups = [group for group in groups + [models64] if group]
        for batch in batches:
            start = time.perf_counter()
            summary = summarise_times(interleaved({**our_calls(body, batch), **anny_calls(groups[0], batch)}, rounds)
                                      if groups else interleaved(our_calls(body, batch), rounds))
            for group in groups[1:]:   # each timed with ours in a group of its own (see ANNY_GROUPS)
                calls = {"ours": our_calls(body, batch)["ours"], **anny_calls(group, batch)}
                summary.update({k: v for k, v in summarise_times(interleaved(calls, rounds)).items() if k != "ours"})
            entry["batches"][batch] = summary
            log(f"  {resolution} batch {batch}: "
                + ", ".join(f"{k} {v['median_ms']:.2f} ms ({v['page_faults']:.0f} faults)" for k, v in summary.items())
                + f" ({time.perf_counter() - start:.0f} s)")
        results[resolution] = entry
    return results


def file_megabytes(path: Path) -> float:
    return path.stat().st_size / 1e6


def sizes(resolutions, weights: dict | None = None, cache_dir: str | None = None, anny: bool = True) -> dict:
    """Our weights files (as given and re-saved in float32) and Anny's model data, MB."""
    weights = weights or {}
    out = {}
    for resolution in resolutions:
        path = Path(weights.get(resolution, shipped_weights(resolution)))
        body = load_body_model(path)
        data = torch.load(path, map_location="cpu", weights_only=True)
        with tempfile.TemporaryDirectory() as tmp:
            save_body_model(body, Path(tmp) / "f32.pt")
            f32 = file_megabytes(Path(tmp) / "f32.pt")
            save_body_model(body, Path(tmp) / "f16.pt", half=True)
            f16 = file_megabytes(Path(tmp) / "f16.pt")
        numbers = sum(v.numel() for v in body.state_dict().values() if v.is_floating_point())
        entry = {"file": str(path), "megabytes": round(file_megabytes(path), 2), "float16": bool(data.get("half", False)),
                 "float16_megabytes": round(f16, 2), "float32_megabytes": round(f32, 2), "numbers": numbers}
        if anny:
            try:
                from humotion.body.anny_source import DEFAULT_RIG, TOPOLOGIES, _import_anny

                anny_module = _import_anny(cache_dir)
                model = anny_module.Anny(rig=DEFAULT_RIG, topology=TOPOLOGIES[resolution], facial_actions="all",
                                         skinning_method="dqs")
                tensors = list(model.buffers()) + list(model.parameters())
                entry["anny_tensors_megabytes"] = round(sum(t.numel() * t.element_size() for t in tensors) / 1e6, 2)
                entry["anny_tensors_dtype"] = str(model.dtype).replace("torch.", "")
                root = Path(anny_module.__file__).parent / "data"
                entry["anny_data_folder_megabytes"] = round(sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
                                                            / 1e6, 1)
            except ImportError:
                pass
        out[resolution] = entry
    return out


def markdown(header: list[str], rows: list[list]) -> str:
    fmt = lambda x: f"{x:.2f}" if isinstance(x, float) else str(x)  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(fmt(x) for x in row) + " |" for row in rows])


def speed_markdown(results: dict) -> str:
    present = {n for entry in results.values() for summary in entry["batches"].values() for n in summary}
    anny = [n for n, _ in ANNY + ANNY_FLOAT64 if n in present]
    names = [n for n, _ in OURS] + anny
    rows = []
    for resolution, entry in results.items():
        for batch, summary in entry["batches"].items():
            row = [resolution, entry["vertices"], batch]
            row += [summary[n]["median_ms"] if n in summary else "-" for n in names]
            row += [f"{summary[n]['ratio_to_ours']:.1f}x" if n in summary else "-" for n in anny]
            rows.append(row)
    header = ["resolution", "vertices", "batch", *[f"{n} (ms)" for n in names], *[f"{n} / ours" for n in anny]]
    return markdown(header, rows)


def faults_markdown(results: dict) -> str:
    present = {n for entry in results.values() for summary in entry["batches"].values() for n in summary}
    names = [n for n, _ in OURS + ANNY + ANNY_FLOAT64 if n in present]
    rows = [[resolution, batch, *[f"{summary[n]['page_faults']:.0f}" if n in summary else "-" for n in names]]
            for resolution, entry in results.items() for batch, summary in entry["batches"].items()]
    return markdown(["resolution", "batch", *names], rows)


def sizes_markdown(result: dict) -> str:
    rows = [[r, e["file"], e["megabytes"], e["float16_megabytes"], e["float32_megabytes"], e["numbers"],
             e.get("anny_tensors_megabytes", "-"), e.get("anny_data_folder_megabytes", "-")] for r, e in result.items()]
    return markdown(["resolution", "weights file", "MB", "MB (float16 storage)", "MB (float32)", "numbers",
                     "Anny model tensors (MB, float64)", "Anny data folder (MB, all topologies)"], rows)


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--resolution", "resolutions", type=click.Choice(["low", "full"]), multiple=True,
              help="Resolutions to time (default: both).")
@click.option("--low", "low_path", help="Low-resolution weights (default: the shipped ones).")
@click.option("--full", "full_path", help="Full-resolution weights (default: the shipped ones).")
@click.option("--batches", default="1,64", show_default=True)
@click.option("--rounds", default=21, show_default=True, help="Interleaved rounds per batch size.")
@click.option("--threads", default=1, show_default=True)
@click.option("--anny-cache", help="Anny's model cache (default $ANNY_CACHE_DIR or ~/.cache/anny).")
@click.option("--float64", is_flag=True, help="Also time Anny as built (float64, default skinning), for reference.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Also write the results as JSON.")
def main(resolutions, low_path, full_path, batches, rounds, threads, anny_cache, float64, json_path):
    """Forward-pass time of ours vs Anny's at the same resolution, and model sizes."""
    torch.set_num_threads(threads)
    resolutions = resolutions or ("low", "full")
    weights = {k: v for k, v in (("low", low_path), ("full", full_path)) if v}
    batches = [int(b) for b in batches.split(",")]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), float32, {rounds} interleaved rounds",
          file=sys.stderr)
    results = {"threads": threads, "rounds": rounds,
               "speed": speed_table(resolutions, batches, rounds, cache_dir=anny_cache, weights=weights,
                                    log=lambda s: print(s, file=sys.stderr, flush=True), float64=float64)}
    skinning = {r: e["anny_skinning"] for r, e in results["speed"].items()}
    print(f"\n## Forward pass, ms per call (median of {rounds} interleaved rounds; CPU, {threads} thread(s), "
          f"float32)\n")
    print(speed_markdown(results["speed"]))
    print("\nAnny's skinning functions: " + "; ".join(f"{k} = {v}" for k, v in next(iter(skinning.values()), {}).items())
          + ". Ratios: median over rounds of Anny / ours (with correctives) timed in the same round; "
          "Anny DQS and LBS interleaved with ours apart from the rest.")
    print("\n## Page faults per timed call (median over rounds)\n")
    print(faults_markdown(results["speed"]))
    results["sizes"] = sizes(resolutions, weights, anny_cache)
    print("\n## Size\n")
    print(sizes_markdown(results["sizes"]))
    if json_path:
        Path(json_path).write_text(json.dumps(results, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
