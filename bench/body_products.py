"""The body model's mesh-wide products on this CPU: one product against column pieces
(humotion.body.model.wide_addmm) and against the vertex-major layout, and the vertex-major
product in float32 (torch) against float16 (compiled).

    .venv/bin/python bench/body_products.py [--rounds 9]

One CPU thread, float32, no gradients. Prints, per batch size B, the medians over rounds of
(B, 64) x (64, 41,154) + offset (the full-resolution shape decoding's product) as one torch
product, in pieces (the torch path's planar decoding), with numpy (OpenBLAS, for reference) and
vertex-major (rows x factors^T, a (41,154, B) result: the layout of the CPU inference path,
humotion.body.cpu_posing), with GFLOP/s; then, for a few bodies, that vertex-major product with
the shipped full-resolution shape decoder's own output weight, by torch in float32 against the
CPU path's compiled loop over its float16 copy (humotion.body.cpu_kernels.half_product: the
weights hold float16 numbers exactly), timed alternately, round by round; then mesh_height's
reduction (amax - amin) against one torch.aminmax on a (64, 13,718) plane; then the bones the torch path's skinning blends per block
of 512 vertices of the full-resolution body (linear_blend_skinning's cost is proportional to
them), in the mesh's vertex order and with the vertices sorted by the set of bones that weigh on
them. (The forward pass at batch 64 with pieces against one product, which earlier releases
printed here, now runs the compiled path, which takes neither.)
"""

from __future__ import annotations

import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # numpy (OpenBLAS) on one thread too

import click
import torch

import humotion.body.model as body_model


def median_ms(call, rounds: int, repeats: int = 3) -> float:
    call()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(repeats):
            call()
        times.append((time.perf_counter() - start) / repeats * 1e3)
    return statistics.median(times)


def one_product(offset, factors, rows):
    return torch.addmm(offset, factors, rows.T)


def float16_products(rounds: int, generator: torch.Generator) -> None:
    """Print the shipped shape decoder's vertex-major product, float32 (torch, on one thread and
    on two) against float16 (the compiled loop, on one thread, which the CPU path uses up to
    batch 4 with torch on one thread), at batches 1 to 8: medians over interleaved rounds and of
    the per-round ratio."""
    from humotion.body import cpu_kernels
    from humotion.body.cpu_posing import half_bits

    if not cpu_kernels.FLOAT16_IN_HARDWARE:
        print("\nfloat16 products: skipped (numba compiles for a CPU without F16C here)")
        return
    weight = body_model.load_body_model("full").shape_vae.output.weight.detach()       # (41154, 64)
    half = half_bits(weight)
    offset = torch.randn(len(weight), 1, generator=generator)
    print(f"\n## Vertex-major {tuple(weight.shape)} shape product for B bodies, ms: float32 (torch) against "
          "float16 (compiled, one thread)\n")
    print("| B | float32 | float32, torch on 2 threads | float16 | float32 / float16 | largest difference |\n"
          "|---|---|---|---|---|---|")
    for batch in (1, 2, 4, 8):
        factors, out = torch.randn(batch, weight.shape[1], generator=generator), torch.empty(len(weight), batch)
        def single():
            return torch.addmm(offset, weight, factors.T)

        def two_threads():
            torch.set_num_threads(2)
            single()
            torch.set_num_threads(1)
        calls = (single, two_threads,
                 lambda: cpu_kernels.half_product(half, factors.numpy(), offset.numpy(), out.numpy()))
        calls[2]()
        difference = (single() - out).abs().max().item()
        times = [[median_ms(call, 1) for call in calls] for _ in range(rounds)]
        float32_ms, two_ms, float16_ms = (statistics.median(t[i] for t in times) for i in (0, 1, 2))
        ratio = statistics.median(t[0] / t[2] for t in times)
        print(f"| {batch} | {float32_ms:.3f} | {two_ms:.3f} | {float16_ms:.3f} | {ratio:.2f}x | {difference:.1e} |")


@click.command()
@click.option("--rounds", default=9, show_default=True)
def main(rounds):
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(0)
    rows, offset = torch.randn(41154, 64, generator=generator), torch.randn(41154, generator=generator)
    print("## (B, 64) x (64, 41154) + offset, ms (GFLOP/s)\n")
    print("| B | one product | pieces | one / pieces | numpy (OpenBLAS) | vertex-major |\n|---|---|---|---|---|---|")
    for batch in (1, 16, 32, 64, 128):
        factors = torch.randn(batch, 64, generator=generator)
        flops = 2 * batch * 64 * 41154 / 1e6
        a_np, f_np, o_np = rows.numpy().T.copy(), factors.numpy(), offset.numpy()
        one, pieces, numpy_ms, vertex_major = (median_ms(call, rounds) for call in (
            lambda: one_product(offset, factors, rows), lambda: body_model.wide_addmm(offset, factors, rows),
            lambda: f_np @ a_np + o_np, lambda: torch.addmm(offset[:, None], rows, factors.T)))
        print(f"| {batch} | {one:.2f} ({flops / one:.0f}) | {pieces:.2f} ({flops / pieces:.0f}) | {one / pieces:.2f}x "
              f"| {numpy_ms:.2f} ({flops / numpy_ms:.0f}) | {vertex_major:.2f} ({flops / vertex_major:.0f}) |")

    float16_products(rounds, generator)

    plane = torch.randn(64, 13718, generator=generator)
    minmax = median_ms(lambda: torch.aminmax(plane, dim=-1), rounds)
    extent = median_ms(lambda: plane.amax(-1) - plane.amin(-1), rounds)
    print(f"\nmesh_height's reduction on (64, 13718): aminmax {minmax:.3f} ms, amax - amin {extent:.3f} ms "
          f"({minmax / extent:.1f}x)")

    with torch.no_grad():
        weighted = body_model.load_body_model("full").skinning_weights() > 0           # (V, J)
    supports = [tuple(row.nonzero()[:, 0].tolist()) for row in weighted]
    by_bones = sorted(range(len(supports)), key=lambda v: supports[v])
    for name, order in (("mesh order", list(range(len(supports)))), ("sorted by bone set", by_bones)):
        blocks = [weighted[order[start:start + 512]].any(0).sum().item() for start in range(0, len(order), 512)]
        print(f"bones per 512-vertex block, full resolution, {name}: {statistics.mean(blocks):.1f}")


if __name__ == "__main__":
    main()
