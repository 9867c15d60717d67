"""SparsePoser and its losses: shapes, online == batch, masking, mask-token modes, loss terms."""

from dataclasses import FrozenInstanceError, replace

import pytest
import torch

from humotion import rotations as rot
from humotion.sparse import signals as sg
from humotion.sparse.frame import weights_digest
from humotion.sparse.losses import TERMS, loss_weights, sparse_loss, targets
from humotion.sparse.model import (SparseConfig, SparseOutput, SparsePoser, heading, load_sparse_model,
                                   save_sparse_model, sixd_to_matrix)

SMALL = dict(embed=8, hidden=32, layers=1, heads=2, feedforward=32, decoder=32)
B, T = 3, 6


def model(**changes) -> SparsePoser:
    torch.manual_seed(0)
    return SparsePoser(SparseConfig(**{**SMALL, **changes})).eval()


def random_signals(b=B, t=T, seed=1) -> dict:
    """Plausible headset signals from random body poses, hands hidden at random."""
    g = torch.Generator().manual_seed(seed)
    rotations = rot.convert(torch.randn(b, t, 3, 3, generator=g) * 0.5, "rotvec", "matrix")
    positions = torch.randn(b, t, 3, 3, generator=g) * 0.3 + torch.tensor([2.0, 1.5, -1.0])
    visible = torch.rand(b, t, 2, generator=g) > 0.4
    return sg.hide_unseen(sg.pose_signals(rotations, positions, visible))


def test_output_shapes_batched_and_unbatched():
    m, signals = model(), random_signals()
    out = m(signals, aux=True)
    assert out["rotations"].shape == (B, T, 22, 3, 3)
    assert out["sixd"].shape == (B, T, 22, 6)
    assert out["root_positions"].shape == (B, T, 3)
    assert out["forecast"].shape == (B, T, 2, 9)
    assert out["aux"].shape == (B, T, 22, 9)
    single = m({k: v[1] for k, v in signals.items()})
    assert single["rotations"].shape == (T, 22, 3, 3) and single["root_positions"].shape == (T, 3)
    assert torch.allclose(single["root_positions"], out["root_positions"][1], atol=1e-5)
    # Rotations are proper rotation matrices.
    r = out["rotations"]
    assert torch.allclose(r @ r.transpose(-1, -2), torch.eye(3).expand_as(r), atol=1e-5)
    assert torch.allclose(torch.linalg.det(r), torch.ones(()), atol=1e-5)


def test_outputs_read_as_attributes_and_by_name():
    """SparsePoser gives a SparseOutput: each output is the same tensor as an attribute and by
    name (as the dicts it replaced were read), sixd derives from the rotations, and select /
    stack / replace make new outputs."""
    m, signals = model(), random_signals()
    out = m(signals, aux=True)
    assert isinstance(out, SparseOutput)
    assert out.keys() == ("rotations", "root_positions", "positions", "forecast", "aux", "state")
    for name, value in out.items():
        assert out[name] is value is getattr(out, name)
    assert out.positions is None and out.state.t.tolist() == [T] * B
    torch.testing.assert_close(out["sixd"], rot.convert(out.rotations, "matrix", "sixd"), rtol=0, atol=1e-6)
    with pytest.raises(KeyError, match="no 'velocity'"):
        out["velocity"]
    first = out.select(0)
    assert torch.equal(first.aux, out.aux[0]) and first.state is out.state
    frames = [out.select((slice(None), t)) for t in range(T)]
    assert frames[0].rotations.shape == (B, 22, 3, 3)
    assert all(torch.equal(getattr(SparseOutput.stack(frames, 1), name), getattr(out, name))
               for name in ("rotations", "root_positions", "forecast", "aux"))
    with pytest.raises(FrozenInstanceError):
        out.rotations = first.rotations
    with pytest.raises(ValueError, match="same leading dimensions"):
        replace(out, root_positions=first.root_positions)


@pytest.mark.parametrize("mask_token", ["adaptive", "fixed"])
def test_step_by_step_equals_forward(mask_token):
    m, signals = model(mask_token=mask_token), random_signals()
    with torch.no_grad():
        whole = m(signals)
        state, frames = None, []
        for t in range(T):
            out, state = m.step({k: v[:, t] for k, v in signals.items()}, state)
            frames.append(out)
    for key in ("rotations", "root_positions", "forecast"):
        if whole[key] is None:
            assert all(f[key] is None for f in frames)
            continue
        torch.testing.assert_close(torch.stack([f[key] for f in frames], 1), whole[key], rtol=0, atol=1e-6)
    # Continuing a window from a state equals running the whole window at once.
    with torch.no_grad():
        first = m({k: v[:, :2] for k, v in signals.items()})
        rest = m({k: v[:, 2:] for k, v in signals.items()}, state=first["state"])
    torch.testing.assert_close(rest["root_positions"], whole["root_positions"][:, 2:], rtol=0, atol=1e-6)
    # Unbatched frames work too.
    out, _ = m.step({k: v[0, 0] for k, v in signals.items()})
    assert out["rotations"].shape == (22, 3, 3) and out["root_positions"].shape == (3,)


def test_fixed_mask_token_flag():
    fixed, adaptive = model(mask_token="fixed"), model()
    assert hasattr(fixed, "fixed_token") and not hasattr(fixed, "tamt")
    assert hasattr(adaptive, "tamt") and not hasattr(adaptive, "fixed_token")
    assert fixed(random_signals())["forecast"] is None
    with pytest.raises(ValueError):
        SparseConfig(mask_token="learned")


def test_detached_token_trains_tamt_but_not_the_encoder_through_it():
    signals = random_signals()
    signals["visible"][:, 1:] = 0.0                 # hands unseen after the first frame
    # the forecast trains TAMT either way, and the encoder only when the gradient passes TAMT's input
    for mode, reaches_encoder in (("full", True), ("detached", False)):
        m = model(token_gradient=mode).train()
        m(signals)["forecast"].square().sum().backward()
        assert m.tamt[0].weight.grad.abs().sum() > 0
        assert (m.gru.input.weight.grad is not None and m.gru.input.weight.grad.abs().sum() > 0) == reaches_encoder
    # the same function at run time: detaching changes training only (and not the weights'
    # digest, which names their ONNX exports)
    detached, full = model(token_gradient="detached"), model(token_gradient="full")
    with torch.no_grad():
        assert torch.equal(detached(signals)["root_positions"], full(signals)["root_positions"])
    assert weights_digest(detached) == weights_digest(full) != weights_digest(model(hidden=16))
    with pytest.raises(ValueError, match="token_gradient"):
        SparseConfig(token_gradient="half")


@pytest.mark.parametrize("mask_token", ["adaptive", "fixed"])
def test_hidden_hand_values_change_nothing(mask_token):
    m, signals = model(mask_token=mask_token), random_signals()
    signals["visible"][:, :, 0] = 0.0               # left hand never seen
    signals["visible"][:, 2:4, 1] = 0.0             # right hand lost for two frames
    changed = dict(signals)
    for name in ("left", "left_in_head"):
        for key in (name, name + "_vel"):
            changed[key] = signals[key] + torch.randn_like(signals[key]) * 5
    for name in ("right", "right_in_head"):
        for key in (name, name + "_vel"):
            noise = torch.zeros_like(signals[key])
            noise[:, 2:4] = torch.randn(B, 2, 9) * 5
            changed[key] = signals[key] + noise
    with torch.no_grad():
        a, b = m(signals, aux=True), m(changed, aux=True)
    for key in ("rotations", "root_positions", "forecast", "aux"):
        if a[key] is not None:
            assert torch.equal(a[key], b[key]), key
    # ...whereas a visible hand's values do matter.
    signals["visible"][:] = 1.0
    changed["visible"] = signals["visible"]
    with torch.no_grad():
        assert not torch.equal(m(signals)["rotations"], m(changed)["rotations"])


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0, 120.0, 180.0, -90.0])
def test_heading_is_the_yaw_of_a_yaw_then_tilt(yaw_deg):
    """A yaw about +Y followed by a tilt about a horizontal axis (of the turned frame) has
    that yaw as its heading, facing backwards included."""
    yaw = rot.convert(torch.tensor([0.0, torch.pi * yaw_deg / 180, 0.0], dtype=torch.float64), "rotvec", "matrix")
    for tilt in ([0.6, 0.0, 0.0], [0.0, 0.0, -0.4], [0.3, 0.0, 0.5]):
        rotation = yaw @ rot.convert(torch.tensor(tilt, dtype=torch.float64), "rotvec", "matrix")
        torch.testing.assert_close(heading(rotation), yaw, rtol=0, atol=1e-9)


def test_sixd_to_matrix_is_gram_schmidt():
    """The few-node Gram-Schmidt equals humotion.rotations' (roma's) and gives rotations."""
    x = torch.randn(500, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    matrices = sixd_to_matrix(x)
    torch.testing.assert_close(matrices, rot.convert(x, "sixd", "matrix"), rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.det(matrices), torch.ones(500, dtype=torch.float64))


def test_written_out_layers_equal_the_modules_they_stand_for():
    """_embed and _encode (written for a small ONNX graph) compute what the per-part MLPs and
    nn.TransformerEncoder compute, in training mode too (no dropout)."""
    m = model(layers=2, heads=4).train()
    g = torch.Generator().manual_seed(3)
    x, tokens = torch.randn(5, B, 18, generator=g), torch.randn(B, 5, 32, generator=g)
    per_part = torch.cat([m.embed_rotation(x[..., 0:6]), m.embed_position(x[..., 6:9]),
                          m.embed_rotation_velocity(x[..., 9:15]), m.embed_position_velocity(x[..., 15:18])], -1)
    torch.testing.assert_close(m._embed(x), per_part, rtol=0, atol=1e-6)
    torch.testing.assert_close(m._encode(tokens), m.encoder(tokens), rtol=0, atol=1e-5)


def test_where_the_user_stands_does_not_matter():
    m, signals = model(), random_signals()
    moved = sg.recentre(signals, torch.tensor([-3.0, 7.0]))  # shifts world positions by (+3, 0, -7)
    with torch.no_grad():
        a, b = m(signals), m(moved)
    torch.testing.assert_close(b["rotations"], a["rotations"], rtol=0, atol=1e-5)
    torch.testing.assert_close(b["root_positions"], a["root_positions"] + torch.tensor([3.0, 0, -7.0]), rtol=0, atol=1e-4)


def test_save_and_load(tmp_path):
    m, signals = model(mask_token="fixed", hidden=16), random_signals()
    save_sparse_model(m, tmp_path / "w.pt", note="test")
    loaded = load_sparse_model(tmp_path / "w.pt")
    assert loaded.config == m.config and not loaded.training and loaded.fps == 30.0
    with torch.no_grad():
        assert torch.equal(loaded(signals)["rotations"], m(signals)["rotations"])


# -- losses --------------------------------------------------------------------------------

def perfect(target: dict) -> SparseOutput:
    body6 = rot.convert(target["body_rotations"], "matrix", "sixd")
    return SparseOutput(target["rotations"].clone(), target["root_positions"].clone(), forecast=target["hands"].clone(),
                        aux=torch.cat([body6, target["body_positions"]], -1))


def random_target(seed=0) -> dict:
    g = torch.Generator().manual_seed(seed)
    local = rot.convert(torch.randn(2, 5, 22, 3, generator=g) * 0.3, "rotvec", "matrix")
    root = torch.randn(2, 5, 3, generator=g)
    offsets = torch.randn(2, 22, 3, generator=g) * 0.2
    return targets(local, root, offsets, hands=torch.randn(2, 5, 2, 9, generator=g))


def test_a_file_that_holds_no_such_weights_is_named(tmp_path):
    (tmp_path / "take.bvh").write_text("HIERARCHY\n")
    torch.save({"config": {}, "state_dict": {"x": torch.zeros(1)}}, tmp_path / "other.pt")
    for name in ("take.bvh", "other.pt"):
        with pytest.raises(ValueError, match=f"{name} is not a SparsePoser weights file"):
            load_sparse_model(tmp_path / name)


def test_every_loss_is_zero_for_a_perfect_prediction_and_positive_otherwise():
    target = random_target()
    total, terms = sparse_loss(perfect(target), target)
    assert set(terms) == set(TERMS)
    for name, value in terms.items():
        assert float(value) < 1e-10, name
    spoiled = {name: perfect(target) for name in TERMS}
    spoiled["data"].root_positions[:] += 0.1
    spoiled["smooth"].root_positions[:, 2:] += 0.1
    spoiled["se3"].rotations[..., 3, :, :] = rot.convert(torch.tensor([0.0, 0.3, 0.0]), "rotvec", "matrix")
    spoiled["forecast"].forecast[:, 3] += 0.1
    spoiled["aux"].aux[..., 6:] += 0.1
    for name in TERMS:
        _, terms = sparse_loss(spoiled[name], target)
        assert float(terms[name]) > 1e-4, name
    # A change on the first frame is no forecast error (nothing to forecast from).
    first = perfect(target)
    first.forecast[:, 0] += 1.0
    assert float(sparse_loss(first, target)[1]["forecast"]) == 0.0


def test_switching_a_loss_off_removes_it():
    target = random_target()
    pred = perfect(target)
    pred = replace(pred, root_positions=pred.root_positions + 0.1,
                   aux=None)  # a term that is off is never computed, so its input may be missing
    weights = loss_weights(ablate=("aux", "smooth"))
    total, terms = sparse_loss(pred, target, weights)
    assert set(terms) == {"data", "se3", "forecast"}
    assert torch.isclose(total, sum(terms.values()))
    with pytest.raises(ValueError):
        sparse_loss(pred, target)  # aux on but no aux outputs
    with pytest.raises(ValueError):
        loss_weights(ablate=("data",))
    with pytest.raises(ValueError):
        loss_weights(ablate=("smoothness",))
    half = sparse_loss(pred, target, loss_weights(ablate=("aux",), se3=0.5))
    assert torch.isclose(half[0], half[1]["data"] + half[1]["smooth"] + 0.5 * half[1]["se3"] + half[1]["forecast"])


def test_position_weight_scales_only_the_position_part_of_the_transform_terms():
    target = random_target()
    moved = perfect(target)
    moved = replace(moved, root_positions=moved.root_positions + 0.1)      # every joint 10 cm off, no bone turned
    moved.aux[..., 6:] += 0.1
    _, plain = sparse_loss(moved, target)
    _, heavy = sparse_loss(moved, target, position_weight=10.0)
    for name in ("se3", "aux"):
        assert float(plain[name]) == pytest.approx(0.03, rel=1e-4)        # 3 x (0.1 m)^2
        assert float(heavy[name]) == pytest.approx(10 * float(plain[name]), rel=1e-5)
    assert torch.isclose(heavy["data"], plain["data"]) and torch.isclose(heavy["smooth"], plain["smooth"])
    turned = perfect(target)
    turned.rotations[..., 3, :, :] = rot.convert(torch.tensor([0.0, 0.3, 0.0]), "rotvec", "matrix")
    _, a = sparse_loss(turned, target)
    _, b = sparse_loss(turned, target, position_weight=10.0)
    rotation_part = a["se3"] - (b["se3"] - a["se3"]) / 9              # what is left with positions weighted 0
    assert 0 < float(rotation_part) < float(a["se3"])


def test_losses_train_the_model_end_to_end():
    """Gradients reach every parameter used by the losses."""
    m = model().train()
    signals = random_signals(b=2, t=5)
    target = random_target()
    target["hands"] = torch.stack([signals["left"], signals["right"]], -2)
    total, _ = sparse_loss(m(signals), target)
    total.backward()
    missing = [n for n, p in m.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing, missing
