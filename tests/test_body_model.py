"""The learned body model (humotion.body.model, .train, .joints, .correctives, .limits): the
shipped weights, the forward pass, input checks, and a tiny training run on a toy data folder
made by the shipped model itself (no Anny, no data download)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from humotion.body import files
from humotion.body.anthropometry import mesh_height
from humotion.body.checks import checked_tensor
from humotion.body.model import BodyModel, interpolate, load_body_model, shipped_weights
from humotion.body.skinning import linear_blend_skinning, skinning_transforms

RESOLUTIONS = [r for r in ("low", "full") if shipped_weights(r).exists()]
needs_weights = pytest.mark.skipif("low" not in RESOLUTIONS, reason="no shipped body weights")


@pytest.fixture(scope="module")
def low():
    if "low" not in RESOLUTIONS:
        pytest.skip("no shipped body weights")
    torch.set_num_threads(1)
    return load_body_model("low")


@pytest.fixture(scope="module", params=RESOLUTIONS or ["low"])
def body(request):
    if request.param not in RESOLUTIONS:
        pytest.skip("no shipped body weights")
    torch.set_num_threads(1)
    return load_body_model(request.param)


def random_pose(body: BodyModel, count: int, scale: float = 0.5, seed: int = 0) -> torch.Tensor:
    """(count, J, 3) rotation vectors inside the model's joint limits."""
    generator = torch.Generator().manual_seed(seed)
    free = scale * torch.randn(count, body.num_joints, 3, generator=generator)
    return body.limits.to_rotvec(free)


# -- the forward pass ---------------------------------------------------------------------------------

@pytest.mark.parametrize("batch", [1, 8])
def test_forward_shapes_and_dtypes(body, batch):
    c = body.config
    shape = body.sample_shapes(batch, torch.Generator().manual_seed(1))
    expression = body.sample_expressions(batch, torch.Generator().manual_seed(2))
    out = body(shape=shape, expression=expression, pose=random_pose(body, batch), translation=torch.zeros(batch, 3))
    V, J = c.num_vertices, len(c.joint_names)
    assert out.vertices.shape == (batch, V, 3) and out.joints.shape == (batch, J, 3)
    assert out.rest_vertices.shape == (batch, V, 3) and out.world_rotations.shape == (batch, J, 3, 3)
    assert all(x.dtype == torch.float32 for x in (out.vertices, out.joints, out.rest_vertices))
    assert body.faces.shape == (c.num_faces, 3) and int(body.faces.max()) < V
    assert J == 76 and V == {"low": 1229, "full": 13718}[c.resolution]
    assert torch.isfinite(out.vertices).all()


@pytest.mark.parametrize("rows", [None, 100])
@pytest.mark.parametrize("parts", ["all", "no expression", "no correctives"])
def test_forward_is_the_sum_of_its_parts_under_dense_skinning(low, monkeypatch, rows, parts):
    """The forward pass builds and skins the mesh block by block of vertices (100 here: 13 blocks
    of the low body, several of them touching the face); the result must be rest + expression +
    correctives skinned with the dense weights, both without a gradient to keep (the compiled CPU
    path, humotion.body.cpu_posing) and with one (torch)."""
    from humotion.body import cpu_posing, torch_posing

    if rows:
        monkeypatch.setattr(torch_posing, "block_rows", lambda count, num_vertices, device: rows)
        monkeypatch.setattr(cpu_posing, "vertex_block_rows", lambda count: rows)
    generator = torch.Generator().manual_seed(9)
    shape = low.sample_shapes(3, generator)
    expression = None if parts == "no expression" else low.sample_expressions(3, generator)
    rotations = low.pose_matrices(random_pose(low, 3, seed=5))
    translation = 0.1 * torch.randn(3, 3, generator=generator)
    on = parts != "no correctives"
    with torch.no_grad():
        out = low(shape=shape, expression=expression, pose=rotations, translation=translation, correctives=on)
        rest, rest_joints = low.decode_shape_and_joints(shape)
        surface = rest + (0 if expression is None else low.decode_expression(expression))
        surface = surface + (low.corrective_offsets(rotations, rest) if on else 0)
        A, t, joints = skinning_transforms(rest_joints, low.parents, rotations, translation)
        dense = low.skinning_weights().expand(3, -1, -1).double()    # (K, V, J): no blocks
        expected = linear_blend_skinning(surface.double(), dense, A.double(), t.double())
    assert (out.vertices.double() - expected).abs().max() < 2e-6
    assert (out.joints - joints).abs().max() < 1e-6 and (out.rest_vertices - rest).abs().max() < 1e-6
    with torch.enable_grad():   # a gradient to keep: the blocks are joined, not written into one result
        kept = low(shape=shape.clone().requires_grad_(True), expression=expression, pose=rotations,
                   translation=translation, correctives=on)
    assert kept.vertices.requires_grad and (kept.vertices.double() - expected).abs().max() < 2e-6
    if expression is not None:   # a gradient through the face's expression only
        latent = expression.clone().requires_grad_(True)
        with torch.enable_grad():
            face_only = low(shape=shape, expression=latent, pose=rotations, translation=translation, correctives=on)
            face_only.vertices.square().sum().backward()
        assert torch.equal(face_only.vertices.detach(), kept.vertices.detach()) and latent.grad.abs().sum() > 0


@pytest.mark.parametrize("batches", [(1, 1, 1), (3, 3, 3), (5, 5, 5), (5, 1, 5), (5, 5, 1), (5, 0, 5)],
                         ids=["single", "batch of 3", "batch of 5", "one shape", "one expression", "rest mesh given"])
def test_compiled_cpu_path_matches_torch(body, batches, monkeypatch):
    """Without a gradient to keep, the CPU forward pass is humotion.body.cpu_posing's compiled
    loop over vertex-major meshes; with one, torch's blocks. Both must give the same bodies,
    whichever inputs broadcast (a batch-1 shape or expression against a batch of poses) and with
    a rest mesh given instead of a shape (batch size 0 here). Torch's thread count is reported as
    one, so that batches up to 4 take the float16 products whatever the machine."""
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    poses, shapes, expressions = batches
    generator = torch.Generator().manual_seed(11)
    inputs = dict(expression=body.sample_expressions(expressions, generator),
                  pose=random_pose(body, poses, seed=12), translation=0.1 * torch.randn(poses, 3, generator=generator))
    if shapes:
        inputs["shape"] = body.sample_shapes(shapes, generator)
    else:
        inputs["rest_vertices"] = body.decode_shape(body.sample_shapes(poses, generator)) + 0.001
    for correctives in (True, False):
        with torch.no_grad():
            compiled = body(**inputs, correctives=correctives)
        lifted = dict(inputs, translation=inputs["translation"].clone().requires_grad_(True))
        with torch.enable_grad():
            reference = body(**lifted, correctives=correctives)
        assert reference.vertices.requires_grad and not compiled.vertices.requires_grad
        for name in ("vertices", "joints", "rest_vertices", "rest_joints", "world_rotations", "translations"):
            a, b = getattr(compiled, name), getattr(reference, name).detach()
            assert a.shape == b.shape and (a - b).abs().max() < 1e-6, name
    from humotion.body.cpu_posing import uses_float16

    if uses_float16(poses):   # the float16 copies were read (with F16C; batches up to 4)
        assert body.derived.kept("float16/correctives")["float16/correctives"] is not None


def test_float16_products_match_torch_and_are_refused_where_inexact(monkeypatch):
    """The compiled path multiplies by float16 copies of the big weight matrices up to batch
    HALF_PRODUCT_BATCH with torch on one thread, where the CPU converts float16 in hardware (the
    shipped weights hold float16 numbers exactly); above it, on more threads, or for a matrix
    float16 cannot hold, torch's float32 product."""
    from humotion.body import cpu_kernels
    from humotion.body.cpu_posing import HALF_PRODUCT_BATCH, half_bits, rows_product, uses_float16

    g = torch.Generator().manual_seed(4)
    weight = torch.randn(999, 24, generator=g).half().float()
    half = half_bits(weight)
    assert half.dtype == np.uint16 and half.shape == (999, 24)
    assert half_bits(weight * (1 + 2 ** -14)) is None         # a bit float16 does not have
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert not uses_float16(1)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert uses_float16(HALF_PRODUCT_BATCH) == cpu_kernels.FLOAT16_IN_HARDWARE
    assert not uses_float16(HALF_PRODUCT_BATCH + 1)
    if not cpu_kernels.FLOAT16_IN_HARDWARE:
        pytest.skip("this CPU has no F16C: the float16 loop is never run here")
    for batch in range(1, HALF_PRODUCT_BATCH + 1):
        factors = torch.randn(batch, 24, generator=g)
        for offset in (None, torch.randn(999, 1, generator=g), torch.randn(999, batch, generator=g)):
            expected = (0 if offset is None else offset.double()) + weight.double() @ factors.double().T
            out = torch.full((999, batch), torch.nan)
            assert rows_product(offset, weight, half, factors, out=out) is out
            assert (out - expected).abs().max() < 1e-5
            assert (rows_product(offset, weight, None, factors) - expected).abs().max() < 1e-5


@pytest.mark.parametrize("case", ["weights float16 cannot hold", "two threads"])
def test_compiled_path_without_float16_products(low, monkeypatch, case):
    """Without the float16 products (a model trained and saved in float32, or torch on more than
    one thread, where its float32 products are used instead), the compiled path poses the same,
    and keeps no float16 copy."""
    import copy

    body = copy.deepcopy(low)
    body.derived.clear()
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2 if case == "two threads" else 1)
    if case != "two threads":
        with torch.no_grad():
            for weight in (body.shape_vae.output.weight, body.expression_vae.output.weight,
                           body.correctives.regressor.weight):
                weight.mul_(1 + 2 ** -14)
    inputs = dict(shape=body.sample_shapes(1, torch.Generator().manual_seed(1)), pose=random_pose(body, 1, seed=2),
                  expression=body.sample_expressions(1, torch.Generator().manual_seed(3)))
    with torch.no_grad():
        compiled = body(**inputs)
    assert all(value is None for value in body.derived.kept("float16/").values())
    with torch.enable_grad():
        reference = body(**dict(inputs, shape=inputs["shape"].clone().requires_grad_(True)))
    assert (compiled.vertices - reference.vertices.detach()).abs().max() < 1e-6


def test_parameters_replaced_by_a_load_are_the_ones_looked_at(low):
    """The model keeps its parameters in tuples for the per-call check of whether a gradient is
    wanted; load_state_dict(assign=True) replaces the parameters, and the tuples must follow."""
    import copy

    body = copy.deepcopy(low)
    body.load_state_dict({k: v.clone() for k, v in body.state_dict().items()}, assign=True)
    body.requires_grad_(True)
    out = body(shape=torch.zeros(1, body.config.shape_latent), pose=random_pose(body, 1, seed=1))
    assert out.vertices.requires_grad            # the torch path: the new parameters want gradients


def test_compiled_path_on_a_cpu_without_float16_conversion(tmp_path):
    """Where numba compiles for a CPU without F16C (NUMBA_CPU_NAME=generic, as set for caches
    shared between machines), a float16 conversion in a loop would crash the process: the CPU
    path must keep to float32 there, and pose as the torch path does."""
    script = """
import torch
from humotion.body import cpu_kernels
from humotion.body.model import load_body_model
torch.set_num_threads(1)
body = load_body_model("low")
g = torch.Generator().manual_seed(0)
for batch in (1, 3):
    inputs = dict(shape=body.sample_shapes(batch, g), expression=body.sample_expressions(batch, g),
                  pose=0.3 * torch.randn(batch, body.num_joints, 3, generator=g))
    with torch.no_grad():
        compiled = body(**inputs).vertices
    reference = body(**dict(inputs, shape=inputs["shape"].requires_grad_(True))).vertices.detach()
    print(batch, float((compiled - reference).abs().max()))
print("float16", cpu_kernels.FLOAT16_IN_HARDWARE)
"""
    env = dict(os.environ, NUMBA_CPU_NAME="generic", NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.split("\n")
    assert "float16 False" in lines
    assert all(float(line.split()[1]) < 1e-6 for line in lines if line[:2] in ("1 ", "3 "))


def test_kernels_compile_where_numba_can_write_no_cache():
    """numba refuses cache=True where it can write no cache (a read-only install without a home
    directory; here a function without a source file); the CPU path's kernels then compile
    without one instead of failing."""
    from numba import njit

    from humotion.kernels import compiled

    namespace: dict = {}
    exec("def add_one(x):\n    return x + 1\n", namespace)
    with pytest.raises(RuntimeError, match="no locator"):
        njit(cache=True)(namespace["add_one"])
    assert compiled(namespace["add_one"])(41) == 42


def test_rest_pose_reproduces_the_decoded_rest_shape(body):
    shape = body.sample_shapes(3, torch.Generator().manual_seed(3))
    identity = torch.eye(3).expand(3, body.num_joints, 3, 3)
    out = body(shape=shape, pose=identity)
    assert torch.allclose(out.vertices, body.decode_shape(shape), atol=1e-5)
    assert torch.allclose(out.joints, out.rest_joints, atol=1e-6)
    # the zero expression latent is the neutral face, exactly
    zero = body(shape=shape, pose=identity, expression=torch.zeros(3, body.config.expression_latent))
    assert torch.allclose(zero.vertices, out.vertices, atol=1e-6)


def test_pose_forms_agree(low):
    rotvec = random_pose(low, 2, seed=4)
    matrices = low(pose=low.pose_matrices(rotvec)).vertices
    from humotion import rotations as rot
    quats = low(pose=rot.convert(rotvec, "rotvec", "quat")).vertices
    assert torch.allclose(low(pose=rotvec).vertices, matrices, atol=1e-5)
    assert torch.allclose(quats, matrices, atol=1e-5)
    single = low(pose=rotvec[0]).vertices
    assert single.shape == (1, low.num_vertices, 3) and torch.allclose(single[0], matrices[0], atol=1e-5)


def test_rotating_one_joint_moves_only_the_vertices_it_skins(low):
    elbow = low.joint_names.index("lowerarm01.L")
    subtree = {elbow}
    for j, p in enumerate(low.parents):
        if p in subtree:
            subtree.add(j)
    pose = torch.zeros(1, low.num_joints, 3)
    pose[0, elbow] = torch.tensor([0.0, 0.0, 1.2])
    rest = low(correctives=False)
    bent = low(pose=pose, correctives=False)
    moved = (bent.vertices - rest.vertices)[0].norm(dim=-1) > 1e-6
    skinned = low.skinning_weights()[:, sorted(subtree)].sum(1) > 0
    assert moved.any() and not (moved & ~skinned).any()
    # the same through the pure skinning functions, numpy in, numpy out
    weights = np.zeros((3, 2))
    weights[:, 0], weights[2] = 1.0, [0.5, 0.5]
    rest_joints = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rotations = np.broadcast_to(np.eye(3), (1, 2, 3, 3)).copy()
    rotations[0, 1] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90 degrees about Z
    A, t, joints = skinning_transforms(rest_joints, [-1, 0], rotations, np.zeros((1, 3)))
    vertices = np.array([[0.5, 0.1, 0.0], [-0.5, 0.0, 0.2], [2.0, 0.0, 0.0]])
    posed = linear_blend_skinning(vertices, weights, A, t)
    assert np.allclose(posed[0, :2], vertices[:2]) and not np.allclose(posed[0, 2], vertices[2])
    assert np.allclose(posed[0, 2], 0.5 * vertices[2] + 0.5 * np.array([1.0, 1.0, 0.0]))


def test_forward_kinematics_by_level_matches_the_skeleton_one(low):
    from humotion import rotations as rot
    from humotion.skeleton import forward_kinematics_by_level
    from humotion.skeleton import forward_kinematics

    generator = torch.Generator().manual_seed(9)
    local = rot.convert(torch.randn(2, low.num_joints, 3, generator=generator, dtype=torch.float64), "rotvec", "matrix")
    local.requires_grad_(True)
    root, offsets = torch.randn(2, 3, dtype=torch.float64), torch.randn(2, low.num_joints, 3, dtype=torch.float64)
    expected = forward_kinematics(local, root, offsets, low.parents)
    got = forward_kinematics_by_level(local, root, offsets, low.parents)
    for a, b in zip(expected, got):
        assert torch.allclose(a, b, atol=1e-12)
    grad_a = torch.autograd.grad(sum(x.square().sum() for x in expected), local)[0]
    grad_b = torch.autograd.grad(sum(x.square().sum() for x in got), local)[0]
    assert torch.allclose(grad_a, grad_b, atol=1e-10)


def test_joint_regressor_is_sparse_and_inside_the_body(body):
    dense = body.joint_regressor.dense()
    assert dense.shape == (body.num_joints, body.num_vertices)
    assert (dense != 0).sum(1).max() <= body.config.joint_support
    assert (dense != 0).float().mean() < 0.06
    assert torch.allclose(dense.sum(1), torch.ones(body.num_joints), atol=1e-4)  # affine: moves with the mesh
    shape = body.sample_shapes(4, torch.Generator().manual_seed(5))
    rest = body.decode_shape(shape)
    joints = body.rest_joints(rest)
    low, high = rest.amin(1, keepdim=True), rest.amax(1, keepdim=True)
    assert ((joints >= low) & (joints <= high)).all()


def test_joints_decoded_with_the_shape_match_the_regressor_on_the_mesh(body):
    # the forward pass sums the joint regressor over the decoder's weights instead of the mesh
    shape = body.sample_shapes(3, torch.Generator().manual_seed(7), temperature=2.0).requires_grad_(True)
    rest, joints = body.decode_shape_and_joints(shape)
    expected = body.rest_joints(rest)
    assert torch.allclose(joints, expected, atol=2e-6)
    grad, = torch.autograd.grad(joints.square().sum(), shape, retain_graph=True)
    grad_expected, = torch.autograd.grad(expected.square().sum(), shape)
    assert torch.allclose(grad, grad_expected, rtol=1e-4, atol=1e-5)
    # the mesh comes as a view of coordinate planes (B, 3, V), the layout skinning reads
    assert rest.transpose(1, 2).is_contiguous()


def test_gradients_reach_pose_shape_expression_and_translation(low):
    shape = torch.zeros(2, low.config.shape_latent, requires_grad=True)
    expression = (0.1 * torch.ones(2, low.config.expression_latent)).requires_grad_(True)
    pose = random_pose(low, 2, seed=6).requires_grad_(True)
    translation = torch.zeros(2, 3, requires_grad=True)
    out = low(shape=shape, expression=expression, pose=pose, translation=translation)
    (out.vertices.square().sum() + out.joints.square().sum()).backward()
    for x in (shape, expression, pose, translation):
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_correctives_are_zero_at_rest_and_grouped(low):
    from humotion.body.correctives import GROUPS

    identity = torch.eye(3).expand(1, low.num_joints, 3, 3)
    rest = low.decode_shape(torch.zeros(1, low.config.shape_latent))
    assert torch.allclose(low.corrective_offsets(identity, rest), torch.zeros_like(rest), atol=1e-7)
    groups = low.correctives.groups
    assert groups.shape == (len(GROUPS), low.num_joints) and groups[:, 0].sum() == 0
    assert torch.all(groups[:, 1:].sum(0) == 1)  # every joint but the root in exactly one group
    names = low.joint_names
    assert groups[GROUPS.index("head"), names.index("eye.L")] == 1
    assert groups[GROUPS.index("left_hand"), names.index("finger2-3.L")] == 1
    assert groups[GROUPS.index("body"), names.index("lowerarm01.R")] == 1
    rotations = low.pose_matrices(random_pose(low, 2, seed=4))
    scale = torch.tensor([1.0, 0.8])
    factors = low.correctives.factors(rotations, scale)
    offsets = (factors @ low.correctives.regressor.weight.T).unflatten(-1, (-1, 3))
    assert torch.allclose(offsets, low.correctives(rotations, scale), atol=1e-9) and offsets.abs().max() > 1e-4


def test_limits_keep_poses_in_their_boxes(low):
    free = 10 * torch.randn(5, low.num_joints, 3)
    rotvec = low.limits.to_rotvec(free)
    assert (low.limits.violation(rotvec) <= 1e-6).all()
    frozen = low.limits.frozen
    assert frozen.any() and not frozen[0]  # twist bones frozen, the root free
    assert torch.allclose(rotvec[:, frozen], torch.zeros_like(rotvec[:, frozen]))
    inside = low.limits.to_rotvec(0.3 * torch.randn(2, low.num_joints, 3))
    assert torch.allclose(low.limits.to_rotvec(low.limits.to_free(inside)), inside, atol=1e-4)


# -- latent spaces and measurements ----------------------------------------------------------------

def test_sampling_and_interpolation(low):
    shapes = low.sample_shapes(16, torch.Generator().manual_seed(7))
    heights = mesh_height(low.decode_shape(shapes))
    assert heights.min() > 0.8 and heights.max() < 2.2 and heights.std() > 0.03
    path = interpolate(shapes[0], shapes[1], 5)
    assert path.shape == (5, low.config.shape_latent)
    assert torch.allclose(path[0], shapes[0]) and torch.allclose(path[-1], shapes[1])
    arc = interpolate(shapes[0], shapes[1], 5, spherical=True)
    assert torch.allclose(arc[-1], shapes[1], atol=1e-5)
    steps = mesh_height(low.decode_shape(path))
    assert torch.all(torch.isfinite(steps))


@needs_weights
def test_shipped_weights_load_without_anny_and_match_a_requested_height(monkeypatch):
    monkeypatch.setitem(sys.modules, "anny", None)  # any import of anny now fails
    for resolution in RESOLUTIONS:
        body = load_body_model(resolution)
        latent = body.shape_from_measurements(height=[1.62, 1.85], weight=[55.0, 90.0])
        measured = body.measure(body.decode_shape(latent))
        assert torch.allclose(measured["height"], torch.tensor([1.62, 1.85]), atol=0.02)
        assert torch.allclose(measured["weight"], torch.tensor([55.0, 90.0]), rtol=0.05)


# -- bad input ------------------------------------------------------------------------------------------

def test_bad_input_names_the_parameter(low):
    c = low.config
    with pytest.raises(ValueError, match="height"):
        low.shape_from_measurements(height=2.6, weight=80.0)
    with pytest.raises(ValueError, match="weight"):
        low.shape_from_measurements(height=1.7, weight=400.0)
    with pytest.raises(ValueError, match="BMI"):
        low.shape_from_measurements(height=1.9, weight=20.0)
    with pytest.raises(ValueError, match="shape"):
        low(shape=torch.zeros(2, c.shape_latent + 1))
    with pytest.raises(ValueError, match="expression"):
        low(expression=torch.zeros(2, 3, c.expression_latent))
    with pytest.raises(ValueError, match="pose"):
        low(pose=torch.zeros(2, 22, 3))
    with pytest.raises(ValueError, match="translation"):
        low(translation=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="shape or rest_vertices, not both"):
        low(shape=torch.zeros(1, c.shape_latent), rest_vertices=low.template[None])
    with pytest.raises(ValueError, match="one body's latent"):
        low.pose_from_canonical(torch.zeros(1, 22, 4).index_fill(-1, torch.tensor([0]), 1.0), torch.zeros(2, c.shape_latent))
    with pytest.raises(ValueError, match="canonical_rotations"):
        low.pose_from_canonical(torch.zeros(4))
    bad = torch.zeros(1, c.shape_latent)
    bad[0, 3] = float("nan")
    with pytest.raises(ValueError, match="shape.*NaN"):
        low(shape=bad)
    pose = torch.zeros(1, low.num_joints, 3)
    pose[0, 5, 1] = float("inf")
    with pytest.raises(ValueError, match="pose.*NaN or infinite"):
        low(pose=pose)
    huge = torch.tensor([3e38, 3e38, -3e38, float("nan")])       # finite numbers whose sum overflows
    assert torch.equal(checked_tensor("huge", huge[:3], low.template), huge[:3])
    with pytest.raises(ValueError, match="huge contains NaN"):
        checked_tensor("huge", huge, low.template)
    with pytest.raises(ValueError, match="batch size"):
        low(shape=torch.zeros(2, c.shape_latent), pose=torch.zeros(3, low.num_joints, 3))
    with pytest.raises(ValueError, match="height"):
        low.shape_from_measurements(height=float("nan"), weight=70.0)


# -- training ---------------------------------------------------------------------------------------------

def make_toy_data(folder, body: BodyModel, shapes: int = 6, poses: int = 3, seed: int = 0) -> None:
    """A body data folder (the files humotion.body.dataset writes, low resolution only) whose
    meshes the given model makes: random shapes, poses inside its limits and expressions."""
    generator = torch.Generator().manual_seed(seed)
    count = shapes * poses
    with torch.no_grad():
        rest = body.decode_shape(body.sample_shapes(shapes, generator))
        rest_joints = body.rest_joints(rest)
        basis = body.decode_expression(0.5 * torch.randn(52, body.config.expression_latent, generator=generator))
        activations = (torch.rand(count, 52, generator=generator) < 0.05) * torch.rand(count, 52, generator=generator)
        shape_id = torch.arange(count) // poses
        rotvec = body.limits.to_rotvec(0.4 * torch.randn(count, body.num_joints, 3, generator=generator))
        translation = 0.02 * torch.randn(count, 3, generator=generator)
        surface = rest[shape_id] + torch.einsum("me,evc->mvc", activations, basis)
        out = body(pose=rotvec, translation=translation, rest_vertices=surface)
        vertices = out.vertices
    from humotion import rotations as rot

    measures = body.measure(rest)
    held_shape = np.arange(shapes) == shapes - 1
    held_pose = np.tile(np.arange(poses) == poses - 1, shapes)
    split = held_shape[shape_id.numpy()].astype(int) + 2 * held_pose
    regions = {f"region_{r}": body.region(r).numpy() for r in ("body", "face", "hands")}
    files.save_npz(folder / "low" / "model.npz", dict(
        faces=body.faces.numpy().astype(np.int32), joint_names=np.array(body.joint_names), parents=np.array(body.parents),
        rest_vertices=rest.numpy(), rest_joints=rest_joints.numpy(), skin_weights=body.skinning_weights().numpy(),
        expression_basis=basis.numpy(), facial_action_names=np.array([f"action{k}" for k in range(52)]),
        part=np.zeros(body.num_vertices, dtype=np.int16), part_names=np.array(["body"]), **regions))
    for k, name in enumerate(files.SPLITS):
        rows = np.flatnonzero(split == k)
        files.save_npz(folder / "low" / f"{name}.npz", dict(
            vertices=vertices[rows].numpy(), mesh_id=rows, shape_id=shape_id[rows].numpy(), pose_id=rows,
            rotations=rot.convert(rotvec[rows], "rotvec", "quat").numpy(), translation=translation[rows].numpy(),
            joints=out.joints[rows].numpy(), expression=activations[rows].numpy()))
    files.save_npz(folder / "shapes.npz", dict(shape_id=np.arange(shapes), held_out=held_shape,
                                               height=measures["height"].numpy(), mass=measures["weight"].numpy()))
    (folder / "manifest.json").write_text(json.dumps({"toy": True}))


def test_tiny_training_run_learns_checkpoints_and_resumes(low, tmp_path):
    from humotion.body.evaluation import load_meshes, summarise, vertex_errors
    from humotion.body.train import BodyData, BodyTrainConfig, initial_model, train
    from humotion.body.model import BodyConfig

    make_toy_data(tmp_path / "data", low)
    settings = dict(data_root=str(tmp_path / "data"), out_dir=str(tmp_path / "run"), resolution="low", batch_size=4,
                    lr=3e-4, lr_warmup=1, warmup_steps=100, pose_start=0, pose_every=1, pose_iterations=3,
                    validation_subjects=1, checkpoint_every=5, threads=1, progress=False,
                    model=BodyConfig(shape_latent=4, expression_latent=4, shape_hidden=64, corrective_hidden=8))
    data = BodyData(tmp_path / "data", "low", validation_subjects=1)
    meshes = load_meshes(tmp_path / "data", "low", "train", shapes=data.train_shapes.numpy())   # those trained on
    torch.manual_seed(0)  # the start train() makes (its session seeds torch with the run's seed)
    start = initial_model(BodyTrainConfig(**settings).model, data, warmup_steps=100)
    # registration error (poses refitted: training re-optimises the poses it learns from)
    before = summarise(vertex_errors(start, meshes, fit_pose=True, iterations=10), start)["all"]
    summary = train(BodyTrainConfig(steps=20, **settings))
    assert summary["step"] == 20 and summary["start_step"] == 0
    trained = load_body_model(tmp_path / "run" / "body.pt")
    after = summarise(vertex_errors(trained, meshes, fit_pose=True, iterations=10), trained)["all"]
    assert after < before
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert any("pose_fit_after_mm" in r for r in log) and any("val" in r for r in log)
    # validation on a training subject kept out of training; the test splits play no part
    held = load_meshes(tmp_path / "data", "low", "train", shapes=data.validation_shapes)
    assert len(data.validation_shapes) == 1 and len(held["vertices"]) > 0
    assert len(data) == len(meshes["vertices"]) and not torch.isin(data.shape_id, held["shape_id"]).any()
    assert all(key.startswith("validation/") or key == "loss" for r in log if "val" in r for key in r["val"])
    fit = [r for r in log if "pose_fit_after_mm" in r][0]
    assert fit["pose_fit_after_mm"] <= fit["pose_fit_before_mm"]
    # resume: a longer run continues from the newest checkpoint
    again = train(BodyTrainConfig(steps=25, **settings))
    assert again["start_step"] == 20 and again["step"] == 25
    assert load_body_model(tmp_path / "run" / "checkpoint-25.pt").config.shape_latent == 4


def test_pose_from_the_canonical_skeleton(low):
    identity = torch.zeros(2, 22, 4)
    identity[..., 0] = 1.0
    rig = low.pose_from_canonical(identity)
    assert rig.shape == (2, low.num_joints, 3, 3)
    out = low(pose=rig)
    arm = out.joints[0, low.joint_names.index("wrist.L")] - out.joints[0, low.joint_names.index("upperarm01.L")]
    assert arm[0] > 0 and abs(float(arm[1])) < 0.02 * float(arm.norm())  # the canonical T-pose: arms level
    with pytest.raises(ValueError, match="canonical_rotations"):
        low.pose_from_canonical(torch.zeros(1, 21, 4))


def test_half_precision_file_loads_back_close_to_the_model(low, tmp_path):
    from humotion.body.model import load_body_model, save_body_model

    save_body_model(low, tmp_path / "f32.pt")
    save_body_model(low, tmp_path / "f16.pt", half=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f16.pt", "f32.pt"]      # no temporary files left
    assert (tmp_path / "f16.pt").stat().st_size < 0.75 * (tmp_path / "f32.pt").stat().st_size
    stored = torch.load(tmp_path / "f16.pt", weights_only=True)
    assert stored["half"] and any(v.dtype == torch.float16 for v in stored["state_dict"].values())
    reloaded = load_body_model(tmp_path / "f16.pt")
    shape = torch.randn(3, low.config.shape_latent, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        expected, got = low(shape).vertices, reloaded(shape).vertices
    assert got.dtype == torch.float32
    assert (got - expected).abs().max() < 1e-3                                     # under a millimetre


# -- weight files ---------------------------------------------------------------------------------------

def write_damaged(path, damage: str) -> None:
    """A weights file at path: the shipped low-resolution one, damaged as named."""
    shipped = shipped_weights("low")
    raw = {"truncated": shipped.read_bytes()[: shipped.stat().st_size // 2], "empty": b"", "text": b"HIERARCHY\n"}
    if damage in raw:
        path.write_bytes(raw[damage])
        return
    file = torch.load(shipped, weights_only=True)
    tensors = file["state_dict"]
    torch.save({"a tensor": torch.zeros(3),
                "no config": {k: v for k, v in file.items() if k != "config"},
                "a tensor missing": dict(file, state_dict={k: v for k, v in tensors.items() if k != "template"}),
                "a tensor too many": dict(file, state_dict=dict(tensors, extra=torch.zeros(1))),
                "a tensor of another size": dict(file, state_dict=dict(tensors, template=torch.zeros(5, 3))),
                }[damage], path)


@needs_weights
@pytest.mark.parametrize("damage, problem", [
    ("truncated", "failed reading zip archive"),
    ("empty", "it is empty or ends early"),
    ("text", "it is not a torch file of tensors and plain values"),
    ("a tensor", "it holds a Tensor, not a dict"),
    ("no config", "it holds no config and tensors"),
    ("a tensor missing", r"missing tensors \['template'\]"),
    ("a tensor too many", r"unexpected tensors \['extra'\]"),
    ("a tensor of another size", r"size mismatch for template: .* torch.Size\(\[5, 3\]\)"),
])
def test_a_damaged_weights_file_is_refused_in_one_line_naming_the_problem(tmp_path, damage, problem):
    """load_body_model reads weights through humotion.model_files.load_model_file, the loader of
    every network: a damaged file, or one that does not fit the model, is a ValueError of one line
    naming the file and what is wrong with it."""
    path = tmp_path / "body.pt"
    write_damaged(path, damage)
    with pytest.raises(ValueError, match=problem) as refused:
        load_body_model(path)
    message = str(refused.value)
    assert message.startswith(f"{path} is not a BodyModel weights file: ") and "\n" not in message


def test_another_network_or_no_file_is_named(tmp_path):
    path = tmp_path / "sparse.pt"
    torch.save({"kind": "SparsePoser", "config": {}, "state_dict": {}}, path)
    with pytest.raises(ValueError, match=f"{path} holds SparsePoser weights, not BodyModel weights"):
        load_body_model(path)
    with pytest.raises(FileNotFoundError, match="train them with `humotion train body`"):
        load_body_model(tmp_path / "nowhere.pt")


@needs_weights
def test_a_file_without_latent_statistics_loads_with_the_prior_in_their_place(tmp_path):
    from humotion.body.model import LATENT_STATISTICS

    file = torch.load(shipped_weights("low"), weights_only=True)
    file["state_dict"] = {k: v for k, v in file["state_dict"].items() if k not in LATENT_STATISTICS}
    torch.save(file, tmp_path / "body.pt")
    body = load_body_model(tmp_path / "body.pt")
    latent = body.config.shape_latent
    assert torch.equal(body.shape_latent_mean, torch.zeros(latent))
    assert torch.equal(body.shape_latent_cholesky, torch.eye(latent))
    assert not body.training and not any(p.requires_grad for p in body.parameters())


def test_training_without_validation_subjects_is_refused_up_front():
    # It used to fail after the VAE warm-up, in the first validation: torch.cat() of no meshes.
    from humotion.body.train import BodyTrainConfig

    with pytest.raises(ValueError, match="validation_subjects must be at least 1"):
        BodyTrainConfig(validation_subjects=0)
