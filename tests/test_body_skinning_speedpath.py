"""The blocked linear blend skinning and level-by-level forward kinematics of
humotion.body.skinning against straightforward references: random inputs, every weights form
(dense, with zeros, per mesh, numpy, SkinBlocks), and gradients (gradcheck in float64). No data
needed."""

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.body import skinning as S


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: one thread (threads spinning on a busy machine make gradcheck crawl)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def reference_lbs(vertices, weights, A, t):
    """v'_kv = sum_j w_vj (A_kj v_kv + t_kj), in float64, one einsum per term."""
    vertices, weights, A, t = (x.double() if torch.is_tensor(x) else torch.tensor(np.array(x), dtype=torch.float64)
                               for x in (vertices, weights, A, t))
    vertices = vertices.expand(A.shape[0], *vertices.shape[-2:])
    weights = weights.expand(A.shape[0], *weights.shape[-2:])
    moved = torch.einsum("kjcd,kvd->kvjc", A, vertices) + t[:, None]  # (K, V, J, 3) each bone's image
    return torch.einsum("kvj,kvjc->kvc", weights, moved)


def random_case(count, num_vertices, num_joints, seed, zeros=0.8, dtype=torch.float32):
    """Vertices (K, V, 3), weights (V, J) rows summing to one with a fraction `zeros` of exact
    zeros (in runs of vertices sharing bones, like a body's), rotations A (K, J, 3, 3), t (K, J, 3)."""
    g = torch.Generator().manual_seed(seed)
    vertices = torch.randn(count, num_vertices, 3, generator=g, dtype=dtype)
    weights = torch.rand(num_vertices, num_joints, generator=g, dtype=dtype)
    region = torch.arange(num_vertices)[:, None] * num_joints // num_vertices
    near = (torch.arange(num_joints)[None] - region).abs() <= 2
    keep = near | (torch.rand(num_vertices, num_joints, generator=g) > zeros)
    weights = weights * keep
    weights = weights / weights.sum(1, keepdim=True)
    A = rot.convert(torch.randn(count, num_joints, 3, generator=g, dtype=torch.float64), "rotvec", "matrix").to(dtype)
    t = torch.randn(count, num_joints, 3, generator=g, dtype=dtype)
    return vertices, weights, A, t


@pytest.mark.parametrize("count", [1, 3, 70])
def test_blocked_lbs_matches_the_reference(count):
    # 1,300 vertices: several blocks (of 512 or more) at every batch size, the last one short
    vertices, weights, A, t = random_case(count, 1300, 40, seed=count)
    expected = reference_lbs(vertices, weights, A, t)
    for form in (weights, S.SkinBlocks(weights), S.SkinBlocks(weights, prune=False)):
        got = S.linear_blend_skinning(vertices, form, A, t)
        # a (K, V, 3) view of coordinate planes (K, 3, V)
        assert got.shape == (count, 1300, 3) and got.dtype == torch.float32 and got.transpose(1, 2).is_contiguous()
        assert (got.double() - expected).abs().max() < 1e-5
        # vertices given as such a view skin the same
        planes_view = vertices.transpose(1, 2).contiguous().transpose(1, 2)
        assert torch.equal(S.linear_blend_skinning(planes_view, form, A, t), got)
    # shared vertices (V, 3) and per-mesh weights (K, V, J)
    assert (S.linear_blend_skinning(vertices[0], weights, A, t).double()
            - reference_lbs(vertices[0], weights, A, t)).abs().max() < 1e-5
    per_mesh = weights.expand(count, -1, -1) * torch.linspace(0.5, 1.5, count)[:, None, None]
    got = S.linear_blend_skinning(vertices, per_mesh, A, t)
    assert got.transpose(1, 2).is_contiguous() and (got.double() - reference_lbs(vertices, per_mesh, A, t)).abs().max() < 1e-5


def test_skinning_blocks_computed_on_the_way_keep_a_gradient_from_any_block():
    """skin_in_blocks takes the surface block by block (the body model computes each just before
    it is skinned); a gradient needed by a later block only (the face's expression, say) must be
    kept: the blocks are then joined, not written into one result."""
    vertices, weights, A, t = random_case(2, 1300, 40, seed=4)
    blocks = S.SkinBlocks(weights).blocks(512)
    offset = torch.zeros(2, 3, 1300 - 1024, requires_grad=True)   # moves the last block only

    def surfaces():
        planes = vertices.transpose(1, 2).split(512, dim=-1)
        yield from planes[:2]
        yield planes[2] + offset

    kept = S.skin_in_blocks(surfaces(), blocks, A, t, 1300, gradient=True)
    kept.square().sum().backward()
    assert offset.grad.abs().sum() > 0
    with torch.no_grad():
        written = S.skin_in_blocks(surfaces(), blocks, A, t, 1300, gradient=False)   # one result, no joining
    assert torch.equal(kept.detach(), written)
    assert (written.transpose(1, 2).double() - reference_lbs(vertices, weights, A, t)).abs().max() < 1e-5
    with pytest.raises(ValueError, match="cover 1024 vertices, not 1300"):
        S.skin_in_blocks(vertices.transpose(1, 2).split(512, dim=-1)[:2], blocks, A, t, 1300, gradient=False)


def test_blocked_lbs_numpy_in_numpy_out():
    vertices, weights, A, t = random_case(2, 700, 12, seed=5, dtype=torch.float64)
    vertices, weights, A, t = (x.numpy() for x in (vertices, weights, A, t))
    for v, w in ((vertices, weights), (vertices[0], weights), (vertices, np.broadcast_to(weights, (2, 700, 12)))):
        got = S.linear_blend_skinning(v, w, A, t)
        assert isinstance(got, np.ndarray) and got.dtype == np.float64 and got.shape == (2, 700, 3)
        assert np.abs(got - reference_lbs(v, w, A, t).numpy()).max() < 1e-12


def test_skin_blocks_keep_only_the_bones_in_use():
    _, weights, _, _ = random_case(1, 1300, 40, seed=6, zeros=1.0)
    skin_blocks = S.SkinBlocks(weights)
    blocks = skin_blocks.blocks(512)
    assert skin_blocks.blocks(512) is blocks  # built once per block size
    assert [len(w) for _, w in blocks] == [512, 512, 276]
    for (bones, w), rows in zip(blocks, weights.split(512)):
        assert torch.equal(bones, (rows != 0).any(0).nonzero()[:, 0]) and len(bones) < 40
        assert torch.equal(w, rows[:, bones])
    assert S.SkinBlocks(weights, prune=False).blocks(512)[0][1].shape == (512, 40)


def test_blocked_lbs_gradients(monkeypatch):
    # blocks of 4 vertices so that the tiny case has several, with and without pruned bones
    monkeypatch.setattr(S, "block_rows", lambda count, num_vertices, device: 4)
    vertices, weights, A, t = random_case(2, 10, 6, seed=7, zeros=0.9, dtype=torch.float64)
    inputs = [x.clone().requires_grad_(True) for x in (vertices, weights, A, t)]
    assert torch.autograd.gradcheck(S.linear_blend_skinning, inputs)  # weights needing a gradient: no pruning
    blocks = S.SkinBlocks(weights)
    assert any(len(bones) < 6 for bones, _ in blocks.blocks(4))
    assert torch.autograd.gradcheck(lambda v, a, tt: S.linear_blend_skinning(v, blocks, a, tt),
                                    [inputs[0], inputs[2], inputs[3]])
    per_mesh = weights.expand(2, -1, -1).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(S.linear_blend_skinning, [inputs[0], per_mesh, inputs[2], inputs[3]])
    monkeypatch.undo()  # (V, J) weights of fewer vertices than a block: one product, no SkinBlocks
    assert torch.autograd.gradcheck(S.linear_blend_skinning, inputs)
    assert torch.autograd.gradcheck(lambda v, a, tt: S.linear_blend_skinning(v[0], weights, a, tt),
                                    [inputs[0], inputs[2], inputs[3]])


def test_pruned_blocks_give_the_learned_weights_exact_gradients():
    """Pruning skips zero weights, whose gradient a softmax's logits do not use: the gradient
    reaching LearnedSkinWeights' logits through SkinBlocks is the dense product's."""
    vertices, weights, A, t = random_case(3, 1100, 30, seed=8, dtype=torch.float64)
    skin = S.LearnedSkinWeights(1100, 30, 6).double()
    skin.init_from(weights.numpy(), [-1] + list(range(29)))
    target = torch.randn(3, 1100, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    grads = []
    for pruned in (False, True):
        skin.zero_grad()
        dense = skin()
        assert (dense == 0).any()
        posed = S.linear_blend_skinning(vertices, S.SkinBlocks(dense, prune=pruned), A, t)
        (posed * target).sum().backward()
        grads.append(skin.logits.grad.clone())
    assert torch.allclose(grads[0], grads[1], rtol=1e-10, atol=1e-12)


def test_forward_kinematics_by_level_on_a_rig_not_ordered_by_depth():
    from humotion.skeleton import depth_levels, forward_kinematics, forward_kinematics_by_level

    parents = [-1, 0, 1, 0, 3, 2, 4, 0, 5, 1]
    generator = torch.Generator().manual_seed(10)
    local = rot.convert(torch.randn(4, 10, 3, generator=generator, dtype=torch.float64), "rotvec", "matrix")
    local.requires_grad_(True)
    root, offsets = torch.randn(4, 3, dtype=torch.float64), torch.randn(4, 10, 3, dtype=torch.float64)
    order, sizes, above, inverse = depth_levels(tuple(parents))
    assert order.tolist() == [0, 1, 3, 7, 2, 4, 9, 5, 6, 8] and sizes == [1, 3, 3, 2, 1]
    assert torch.equal(order[inverse], torch.arange(10))
    expected = forward_kinematics(local, root, offsets, parents)
    got = forward_kinematics_by_level(local, root, offsets, parents)
    for a, b in zip(expected, got):
        assert torch.allclose(a, b, atol=1e-12)
    grad_a = torch.autograd.grad(sum(x.square().sum() for x in expected), local)[0]
    grad_b = torch.autograd.grad(sum(x.square().sum() for x in got), local)[0]
    assert torch.allclose(grad_a, grad_b, atol=1e-10)


def test_wide_products_in_pieces_match_one_product():
    from humotion.body.model import wide_addmm

    g = torch.Generator().manual_seed(3)
    rows, factors = torch.randn(1000, 8, generator=g, dtype=torch.float64), torch.randn(5, 8, generator=g, dtype=torch.float64)
    for offset in (torch.randn(1000, generator=g, dtype=torch.float64), torch.randn(5, 1000, generator=g, dtype=torch.float64)):
        expected = torch.addmm(offset, factors, rows.T)
        assert torch.equal(wide_addmm(offset, factors, rows), expected)     # small: one product
        pieces = wide_addmm(offset, factors, rows, piece=64)                # 12 columns a piece, 84 pieces
        assert pieces.shape == (5, 1000) and (pieces - expected).abs().max() < 1e-12
        joined = wide_addmm(offset.clone().requires_grad_(True), factors, rows, piece=64)  # a gradient to keep
        assert joined.requires_grad and torch.equal(joined.detach(), pieces)
        inputs = [x.clone().requires_grad_(True) for x in (offset[..., :40], factors, rows[:40])]
        assert torch.autograd.gradcheck(lambda o, f, r: wide_addmm(o, f, r, piece=16), inputs)  # 14 pieces
