"""The sparse-tracking baselines: the nearest-neighbour lookup and the AvatarPoser-style peer."""

import torch

from humotion import rotations as rot
from humotion.canonical import canonical_skeleton
from humotion.motion import Motion
from humotion.sparse import signals as sg
from humotion.sparse.baselines import KnnPoser
from humotion.sparse.batches import make_batch
from humotion.sparse.model import SparseOutput
from humotion.sparse.peers import AvatarPoserPeer, PeerConfig, peer_loss


def _random_motion(frames: int = 60, seed: int = 0) -> Motion:
    """A synthetic test motion: smooth random joint rotations and a wandering root."""
    g = torch.Generator().manual_seed(seed)
    angles = torch.cumsum(torch.randn(frames, 22, 3, generator=g) * 0.05, 0)
    quats = rot.convert(angles, "rotvec", "quat")
    root = torch.tensor([0.0, 0.95, 0.0]) + torch.cumsum(torch.randn(frames, 3, generator=g) * 0.01, 0)
    return Motion(canonical_skeleton(1.7), quats.float(), root.float(), 30.0)


def test_knn_with_one_neighbour_returns_the_training_pose_of_a_training_frame():
    motion = _random_motion()
    index = KnnPoser.from_motions([motion, _random_motion(seed=1)], k=1)
    out = index(sg.hide_unseen(sg.signals_from_motion(motion)))
    assert isinstance(out, SparseOutput)          # what every row of the bench gives
    assert torch.allclose(out.rotations, motion.rotations_as("matrix"), atol=1e-4)
    assert torch.allclose(out.root_positions, motion.root_positions, atol=1e-4)


def test_knn_handles_hands_never_seen_and_averages_to_rotations():
    motion = _random_motion()
    signals = sg.signals_from_motion(motion)
    signals["visible"][:30, 0] = 0.0                       # left hand unseen for the first second
    out = KnnPoser.from_motions([motion], k=8)(sg.hide_unseen(signals))
    r = out["rotations"]
    assert torch.isfinite(r).all()
    assert torch.allclose(r @ r.transpose(-1, -2), torch.eye(3).expand_as(r), atol=1e-4)


def _batch(b: int = 4, frames: int = 12) -> dict:
    motions = [_random_motion(frames, seed) for seed in range(b)]
    return {"rotations": torch.stack([m.rotations for m in motions]),
            "root_positions": torch.stack([m.root_positions for m in motions]),
            "offsets": torch.stack([m.skeleton.offsets for m in motions]),
            "eye": torch.stack([sg.eye_offset(m.skeleton) for m in motions])}


def test_peer_forward_shapes_and_sliding_windows_match_one_causal_pass():
    torch.manual_seed(0)
    model = AvatarPoserPeer(PeerConfig(window=8, width=32, layers=1, heads=4, feedforward=64, mlp=32)).eval()
    inputs, _ = make_batch(_batch(2, 12), scenario_ht=0.5)
    out = model(inputs)
    assert isinstance(out, SparseOutput)
    assert out.rotations.shape == (2, 12, 22, 3, 3) and out.root_positions.shape == (2, 12, 3)
    assert out.positions.shape == (2, 12, 22, 3) and out.sixd.shape == (2, 12, 22, 6)
    single = model({k: v[0] for k, v in inputs.items()})
    assert single.rotations.shape == (12, 22, 3, 3) and single.positions.shape == (12, 22, 3)
    # Frames inside the first window: the same as one causal pass.
    full = model({k: v[:, :8] for k, v in inputs.items()}, all_frames=True)
    assert torch.allclose(out["rotations"][:, :8], full["rotations"], atol=1e-5)
    # A later frame: from the window of 8 frames ending at it.
    later = model({k: v[:, 4:12] for k, v in inputs.items()}, all_frames=True)
    assert torch.allclose(out["rotations"][:, 11], later["rotations"][:, -1], atol=1e-5)


def test_one_peer_training_step_lowers_the_loss_on_a_tiny_batch():
    torch.manual_seed(0)
    model = AvatarPoserPeer(PeerConfig(window=12, width=32, layers=1, heads=4, feedforward=64, mlp=32))
    batch = _batch(4, 12)
    inputs, target = make_batch(batch, scenario_ht=0.0)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    before, _ = peer_loss(model, inputs, target, batch["eye"])
    optimizer.zero_grad()
    before.backward()
    optimizer.step()
    after, _ = peer_loss(model, inputs, target, batch["eye"])
    assert after < before
