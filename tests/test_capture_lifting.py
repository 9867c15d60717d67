"""Video capture, lifting: synthetic keypoints and cameras, noise, normalisation, the network, training."""

import json
import math
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from humotion.canonical import JOINTS, canonical_skeleton, to_canonical
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import (KEYPOINT_MIRROR, MIN_DEPTH, DetectorNoise, VirtualCamera,
                                        body_keypoints_3d, corrupt, random_camera)
from humotion.capture.lift_data import LiftFrames, make_lift_batch
from humotion.capture.lifting import (Lifter, LiftingConfig, LiveLifter, lift_sequence, lifting_inputs, load_lifter,
                                      normalise, procrustes_align, save_lifter)
from humotion.capture.command import train_lift_command
from humotion.capture.train_lift import LiftTrainConfig, train, validate
from humotion.cli import main
from humotion.io import load_motion
from humotion.motion import Motion
from humotion.training import checkpoints, load_windows

SMALL = LiftingConfig(channels=32, levels=2, dropout=0.0)


def k(name: str) -> int:
    return KEYPOINTS.index(name)


@pytest.fixture(scope="module")
def walk(mocap) -> Motion:
    """CMU 01_01 (BVH) on the canonical body at 30 fps."""
    return to_canonical(load_motion(mocap / "cmu_fairmotion" / "01_01.bvh")).resample(30.0)


@pytest.fixture(scope="module")
def walk_keypoints(walk) -> torch.Tensor:
    return body_keypoints_3d(*walk.world(), walk.skeleton)


# -- keypoints on the body -----------------------------------------------------------------

def test_keypoints_on_the_rest_pose_follow_anthropometry():
    skeleton = canonical_skeleton(1.70)
    points = body_keypoints_3d(*Motion.rest(skeleton).world(), skeleton)[0]
    rest = skeleton.rest_positions()
    for name in ("left_shoulder", "right_elbow", "left_wrist", "right_hip", "left_knee", "right_ankle"):
        torch.testing.assert_close(points[k(name)], rest[JOINTS.index(name)])
    assert float(points[k("left_eye"), 1]) == pytest.approx(0.936 * 1.70, abs=1e-5)      # Winter's eye level
    assert float(points[k("left_eye"), 0] - points[k("right_eye"), 0]) == pytest.approx(0.037 * 1.70, abs=1e-5)
    assert float(points[k("left_ear"), 0]) == pytest.approx(0.0445 * 1.70, abs=1e-5)    # the person's left is +x
    assert points[k("nose"), 2] > points[k("left_eye"), 2] > points[k("left_ear"), 2]    # facing +z
    heel, ankle, toe = points[k("left_heel")], rest[JOINTS.index("left_ankle")], points[k("left_big_toe")]
    assert heel[2] < ankle[2] < toe[2] and heel[1] < ankle[1]
    assert float(toe[2] - heel[2]) == pytest.approx(0.152 * 1.70, abs=1e-3)              # Winter's foot length
    assert toe[0] < ankle[0]                                                             # big toe towards the midline
    mirrored = points[list(KEYPOINT_MIRROR)] * torch.tensor([-1.0, 1.0, 1.0])
    torch.testing.assert_close(mirrored, points, atol=1e-6, rtol=0)                      # left-right symmetric


def test_projection_matches_a_hand_computed_pinhole(walk, walk_keypoints):
    points = walk_keypoints[:60]
    pelvis = walk.world_positions()[0, 0]
    # A level camera 4 m behind the person along -z, looking along +z: camera x = -world x, y = -world y.
    eye = pelvis + torch.tensor([0.0, 0.0, -4.0])
    camera = VirtualCamera.looking_at(eye, pelvis, hfov_deg=60.0, width=1280, height=720)
    pixels, depth = camera.project(points)
    focal = 640 / math.tan(math.radians(30))
    relative = points - eye
    expected = torch.stack([focal * -relative[..., 0] / relative[..., 2] + 640,
                            focal * -relative[..., 1] / relative[..., 2] + 360], dim=-1)
    torch.testing.assert_close(depth, relative[..., 2], atol=1e-5, rtol=0)
    torch.testing.assert_close(pixels, expected, atol=1e-3, rtol=0)
    centre, _ = camera.project(pelvis)
    torch.testing.assert_close(centre, torch.tensor([640.0, 360.0]), atol=1e-3, rtol=0)
    assert bool((pixels[:, k("nose"), 1] < pixels[:, k("left_ankle"), 1]).all())       # image y points down
    torch.testing.assert_close(camera.position, eye, atol=1e-5, rtol=0)


def test_random_cameras_film_the_person(walk, walk_keypoints):
    generator = torch.Generator().manual_seed(0)
    starts = torch.arange(0, walk.num_frames - 42, 20)
    rows = starts[:, None] + torch.arange(42)
    joints, keypoints = walk.world_positions()[rows], walk_keypoints[rows]             # (B, 42, ., 3)
    camera = random_camera(generator, torch.cat([joints, keypoints], dim=-2).flatten(1, 2))
    assert camera.fx.shape == (len(starts),)
    pixels, depth = camera.project(keypoints)
    inside = ((pixels >= 0) & (pixels <= camera.size[:, None, None, :])).all(-1)
    assert float(inside.float().mean()) > 0.99 and bool((depth > MIN_DEPTH).all())
    hfov = torch.rad2deg(2 * torch.atan(camera.width / 2 / camera.fx))
    assert bool(((hfov > 45 - 1e-3) & (hfov < 90 + 1e-3)).all())
    floor = keypoints.flatten(1, 2)[..., 1].amin(1)
    height = camera.position[:, 1] - floor
    assert bool(((height >= 0.3 - 1e-4) & (height <= 2.2 + 1e-4)).all())
    centre = (joints.flatten(1, 2).amin(1) + joints.flatten(1, 2).amax(1)) / 2
    assert bool(((camera.position - centre)[:, [0, 2]].norm(dim=-1) >= 2.5 - 1e-4).all())
    # One set of points: one camera.
    assert random_camera(generator, keypoints[0].flatten(0, 1)).fx.shape == ()


# -- noise and normalisation ---------------------------------------------------------------

def test_corrupt_without_noise_is_the_identity(walk_keypoints):
    camera = VirtualCamera.looking_at(walk_keypoints[0, 0] + torch.tensor([0.0, 0.0, 4.0]), walk_keypoints[0, 0],
                                      90.0, 1280, 720)
    pixels, depth = camera.project(walk_keypoints[:30])
    same, confidence = corrupt(pixels, torch.Generator().manual_seed(1), DetectorNoise.none(), camera.size, depth)
    assert torch.equal(same, pixels) and bool((confidence == 1).all())
    shifted = pixels.clone()
    shifted[3, k("left_wrist"), 0] = 1300.0     # right of the image
    shifted[4, k("nose"), 1] = -5.0             # above it
    _, confidence = corrupt(shifted, torch.Generator(), DetectorNoise.none(), camera.size, depth)
    assert float(confidence[3, k("left_wrist")]) == 0 and float(confidence[4, k("nose")]) == 0
    assert float(confidence.sum()) == confidence.numel() - 2
    behind = depth.clone()
    behind[5, k("right_knee")] = -1.0
    _, confidence = corrupt(pixels, torch.Generator(), DetectorNoise.none(), depth=behind)
    assert float(confidence[5, k("right_knee")]) == 0 and float(confidence.sum()) == confidence.numel() - 1


def test_corrupt_spoils_like_a_detector(walk_keypoints):
    camera = VirtualCamera.looking_at(walk_keypoints[0, 0] + torch.tensor([0.0, 0.0, 4.0]), walk_keypoints[0, 0],
                                      60.0, 1920, 1080)
    pixels, _ = camera.project(walk_keypoints[:30])
    windows = pixels.expand(200, -1, -1, -1)
    clean = DetectorNoise(outliers=0, swaps=0, occluders=0)
    noisy, confidence = corrupt(windows, torch.Generator().manual_seed(2), clean)
    assert bool(((confidence >= 0) & (confidence <= 1)).all())
    assert 0.02 < float((confidence == 0).float().mean()) < 0.06        # dropout 2 % + whole frames 1 %
    box = pixels.amax(-2) - pixels.amin(-2)
    scale = box.prod(-1).sqrt().mean()
    error = (noisy - windows)[confidence > 0]
    # Per axis the error's spread is sigma * s (bias 0.6 and jitter 0.8 of it): hips 0.107, eyes 0.025.
    hips = (noisy - windows)[..., k("left_hip"), :].std() / scale
    eyes = (noisy - windows)[..., k("left_eye"), :].std() / scale
    assert hips == pytest.approx(0.107, rel=0.15) and eyes == pytest.approx(0.025, rel=0.15)
    assert float(error.abs().max()) < 10 * 0.107 * float(scale)


def test_normalise_puts_the_pelvis_at_zero_and_the_farthest_keypoint_at_one():
    generator = torch.Generator().manual_seed(3)
    keypoints = torch.rand((5, 21, 2), generator=generator) * 500 + 100
    confidence = torch.rand((5, 21), generator=generator) * 0.9 + 0.1
    confidence[1, k("left_wrist")] = 0.0
    keypoints[1, k("left_wrist")] = 10_000.0          # missing: ignored however far away
    confidence[2, k("right_hip")] = 0.0               # one hip: the other is the centre
    confidence[3] = 0.0                               # nobody
    normalised, scale, centre = normalise(keypoints, confidence)
    hips = (keypoints[:, k("left_hip")] + keypoints[:, k("right_hip")]) / 2
    for frame in (0, 1, 4):
        torch.testing.assert_close(centre[frame], hips[frame])
        torch.testing.assert_close((normalised[frame, k("left_hip")] + normalised[frame, k("right_hip")]) / 2,
                                   torch.zeros(2), atol=1e-6, rtol=0)
        assert float(normalised[frame].norm(dim=-1).max()) == pytest.approx(1.0, abs=1e-6)
    torch.testing.assert_close(centre[2], keypoints[2, k("left_hip")])
    assert float(normalised[2].norm(dim=-1).max()) == pytest.approx(1.0, abs=1e-6)
    assert torch.equal(normalised[1, k("left_wrist")], torch.zeros(2))
    assert float(scale[3]) == 0 and bool((normalised[3] == 0).all())
    torch.testing.assert_close(normalised[0], (keypoints[0] - centre[0]) * scale[0])
    # Invariant to moving and zooming the image.
    moved, _, _ = normalise(keypoints * 2.5 + torch.tensor([30.0, -70.0]), confidence)
    torch.testing.assert_close(moved, normalised, atol=1e-5, rtol=0)


def test_bad_input_is_refused_with_a_reason(mocap, tmp_path):
    keypoints, confidence = torch.zeros(10, 21, 2), torch.ones(10, 21)
    broken = keypoints.clone()
    broken[4, k("left_knee"), 1] = math.nan
    with pytest.raises(ValueError, match=r"NaN.*'left_knee'"):
        normalise(broken, confidence)
    with pytest.raises(ValueError, match=r"\(\.\.\., 21, 2\).*\(10, 17, 2\)"):
        normalise(torch.zeros(10, 17, 2), torch.ones(10, 17))
    with pytest.raises(ValueError, match="confidence must have shape"):
        normalise(keypoints, torch.ones(10, 20))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        normalise(keypoints, confidence * 2)
    model = Lifter(SMALL)
    with pytest.raises(ValueError, match="NaN"):
        lift_sequence(model, broken, confidence)
    with pytest.raises(ValueError, match="frames >= 1"):
        lift_sequence(model, keypoints[0], confidence[0])
    with pytest.raises(ValueError, match=r"frames >= 9"):
        model(torch.zeros(1, 8, 21, 3))
    with pytest.raises(ValueError, match="causal"):
        LiveLifter(model)
    with pytest.raises(ValueError, match="canonical"):
        cmu = load_motion(mocap / "cmu_fairmotion" / "01_01.bvh").skeleton
        body_keypoints_3d(torch.eye(3).expand(1, 22, 3, 3), torch.zeros(1, 22, 3), cmu)
    with pytest.raises(ValueError, match="21, 2"):
        corrupt(torch.zeros(3, 17, 2), torch.Generator())
    with pytest.raises(FileNotFoundError, match="humotion train lift"):
        load_lifter(tmp_path / "missing.pt")


# -- the network ---------------------------------------------------------------------------

def _randomised(model: Lifter) -> Lifter:
    """The model with random weights everywhere (a new Lifter's last layer is zero)."""
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(0.1 * torch.randn_like(parameter))
    return model.eval()


def _filmed(walk_keypoints, frames: int, seed: int = 0):
    camera = VirtualCamera.looking_at(walk_keypoints[0, 0] + torch.tensor([3.0, 0.2, 3.0]), walk_keypoints[0, 0],
                                      70.0, 1280, 720)
    pixels, depth = camera.project(walk_keypoints[:frames])
    return corrupt(pixels, torch.Generator().manual_seed(seed), image_size=camera.size, depth=depth)


def test_causal_output_does_not_see_later_frames(walk_keypoints):
    torch.manual_seed(0)
    causal = _randomised(Lifter(LiftingConfig(channels=32, levels=3, causal=True)))
    centred = _randomised(Lifter(LiftingConfig(channels=32, levels=3, causal=False)))
    keypoints, confidence = _filmed(walk_keypoints, 60)
    changed = keypoints.clone()
    changed[31:] += 40.0 * torch.randn(changed[31:].shape, generator=torch.Generator().manual_seed(5))
    before, after = lift_sequence(causal, keypoints, confidence), lift_sequence(causal, changed, confidence)
    assert before.shape == (60, 22, 3)
    assert torch.equal(before[:31], after[:31])                        # frames up to 30: untouched
    assert bool(((before[31:] - after[31:]).abs().amax((-1, -2)) > 1e-4).all())
    # The centred model does look ahead (half a window: 13 frames).
    before, after = lift_sequence(centred, keypoints, confidence), lift_sequence(centred, changed, confidence)
    assert torch.equal(before[:31 - 13], after[:31 - 13]) and not torch.equal(before[18:31], after[18:31])
    # Chunks give the same as one pass; a live stream the same as the whole sequence.
    torch.testing.assert_close(lift_sequence(causal, keypoints, confidence, chunk=7),
                               lift_sequence(causal, keypoints, confidence), atol=1e-5, rtol=0)
    live = LiveLifter(causal)
    streamed = torch.stack([live.push(keypoints[t], confidence[t]) for t in range(60)])
    torch.testing.assert_close(streamed, lift_sequence(causal, keypoints, confidence), atol=1e-5, rtol=0)


def test_lifter_is_small_and_its_files_round_trip(tmp_path, walk_keypoints):
    default = Lifter()
    assert sum(p.numel() for p in default.parameters()) < 2_000_000 and default.config.window == 27
    torch.manual_seed(1)
    model = _randomised(Lifter(LiftingConfig(channels=48, levels=2, causal=True)))
    model.fps = 25.0
    save_lifter(model, tmp_path / "lifter.pt", step=7)
    loaded = load_lifter(tmp_path / "lifter.pt")
    assert loaded.config == model.config and loaded.fps == 25.0 and not loaded.training
    keypoints, confidence = _filmed(walk_keypoints, 20)
    torch.testing.assert_close(lift_sequence(loaded, keypoints, confidence),
                               lift_sequence(model, keypoints, confidence))
    out = lift_sequence(loaded, keypoints, confidence)
    assert bool((out[:, 0] == 0).all())                                # pelvis-relative


def test_procrustes_alignment_undoes_a_similarity():
    generator = torch.Generator().manual_seed(4)
    true = torch.randn((3, 22, 3), generator=generator)
    turn = torch.linalg.qr(torch.randn((3, 3, 3), generator=generator)).Q
    turn = turn * torch.linalg.det(turn)[:, None, None]                # proper rotations
    moved = 1.7 * true @ turn + torch.tensor([0.3, -2.0, 5.0])
    torch.testing.assert_close(procrustes_align(moved, true), true, atol=1e-4, rtol=0)


# -- training ------------------------------------------------------------------------------

@pytest.fixture
def config(mocap, tmp_path) -> LiftTrainConfig:
    """Three clips of one CMU subject, every clip for training (one subject: no split)."""
    return LiftTrainConfig(data_root=str(mocap / "cmu_mocgui_s02"), train_split=None, val_split=None, max_clips=3,
                           targets=8, stride=8, batch_size=32, lr=3e-3, lr_decay=1.0, model=SMALL,
                           out_dir=str(tmp_path / "run"), cache_dir=str(tmp_path / "cache"), checkpoint_every=10,
                           log_every=5, progress=False, threads=1)


def test_batches_film_the_windows(config):
    frames = LiftFrames(load_windows(config, None, config.stride))
    assert frames.length == config.length == 9 + 8 - 1 and len(frames) > 10
    joints, keypoints, height = frames.window_points([0, 3, 5])
    assert joints.shape == (3, 16, 22, 3) and keypoints.shape == (3, 16, 21, 3) and height.shape == (3,)
    torch.testing.assert_close(keypoints[..., k("left_wrist"), :], joints[..., JOINTS.index("left_wrist"), :])
    inputs, target = make_lift_batch(joints, keypoints, height, torch.Generator().manual_seed(0), mirror=0.0)
    assert inputs.shape == (3, 16, 21, 3) and target.shape == (3, 16, 22, 3)
    assert bool((target[..., 0, :] == 0).all()) and bool(torch.isfinite(inputs).all())
    # Height units: the bones keep their lengths relative to the body's height, whatever the camera.
    shin = (target[..., JOINTS.index("left_knee"), :] - target[..., JOINTS.index("left_ankle"), :]).norm(dim=-1)
    true = (joints[..., JOINTS.index("left_knee"), :] - joints[..., JOINTS.index("left_ankle"), :]).norm(dim=-1)
    torch.testing.assert_close(shin, true / height[:, None], atol=1e-5, rtol=0)
    _, mirrored = make_lift_batch(joints, keypoints, height, torch.Generator().manual_seed(0), mirror=1.0)
    right = (joints[..., JOINTS.index("right_knee"), :] - joints[..., JOINTS.index("right_ankle"), :]).norm(dim=-1)
    shin = (mirrored[..., JOINTS.index("left_knee"), :] - mirrored[..., JOINTS.index("left_ankle"), :]).norm(dim=-1)
    torch.testing.assert_close(shin, right / height[:, None], atol=1e-5, rtol=0)
    # Without noise or mirroring the inputs are the normalised projections of the keypoints.
    same, _ = make_lift_batch(joints, keypoints, height, torch.Generator().manual_seed(0), DetectorNoise.none(),
                              mirror=0.0)
    assert bool((same[..., 2] == 1).all()) and float(same[..., :2].norm(dim=-1).amax()) == pytest.approx(1, abs=1e-5)


def test_tiny_training_learns_checkpoints_and_resumes(config):
    summary = train(LiftTrainConfig(**{**config.__dict__, "steps": 30}))
    assert summary["step"] == 30 and summary["start_step"] == 0
    out = Path(config.out_dir)
    assert [p.name for p in checkpoints(out)] == ["checkpoint-10.pt", "checkpoint-20.pt", "checkpoint-30.pt"]
    log = [json.loads(line) for line in open(out / "log.jsonl")]
    assert [r["step"] for r in log[:3]] == [5, 10, 15]

    frames = LiftFrames(load_windows(config, None, config.targets))
    torch.manual_seed(123)
    before = validate(Lifter(SMALL), frames, config, torch.device("cpu"))
    after = validate(load_lifter(out / "lifter.pt"), frames, config, torch.device("cpu"))
    assert after["loss"] < 0.7 * before["loss"], (before, after)
    assert after["pa_mpjpe_mm"] < after["mpjpe_mm"]

    resumed = train(LiftTrainConfig(**{**config.__dict__, "steps": 34}))
    assert resumed["start_step"] == 30 and resumed["step"] == 34
    state = torch.load(checkpoints(out)[-1], weights_only=True)
    assert state["step"] == 34 and state["config"]["model"]["levels"] == 2
    assert LiftTrainConfig.from_dict(state["config"]) == LiftTrainConfig(**{**config.__dict__, "steps": 34})
    assert load_lifter(checkpoints(out)[-1]).config == SMALL


def test_command_line(mocap, tmp_path):
    result = CliRunner().invoke(main, ["train", "lift", "--help"])
    assert result.exit_code == 0 and "--causal" in result.output and "--max-clips" in result.output
    args = ["--data", str(mocap / "cmu_mocgui_s02"), "--out", str(tmp_path / "cli"), "--steps", "2",
            "--batch-size", "4", "--max-clips", "1", "--levels", "2", "--channels", "16", "--targets", "4",
            "--causal", "--threads", "1"]
    result = CliRunner().invoke(train_lift_command, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    model = load_lifter(tmp_path / "cli" / "lifter.pt")
    assert model.config == LiftingConfig(channels=16, levels=2, causal=True) and model.fps == 30.0
    state = torch.load(checkpoints(tmp_path / "cli")[-1], weights_only=True)
    assert "hdm05_jointlearning" in state["config"]["exclude"]


def test_lifting_inputs_carry_confidence():
    keypoints = torch.rand(4, 21, 2) * 100
    confidence = torch.rand(4, 21)
    inputs = lifting_inputs(keypoints, confidence)
    assert inputs.shape == (4, 21, 3) and torch.equal(inputs[..., 2], confidence)


def test_raised_arms_keep_their_bones_and_go_up(mocap):
    from humotion.capture.lift_data import raise_arms

    motion = to_canonical(load_motion(mocap / "cmu_fairmotion" / "01_01.bvh"))[100:110]
    rotations, positions = motion.world()
    keypoints = body_keypoints_3d(rotations, positions, motion.skeleton)
    joints, raised_keypoints = raise_arms(positions[None], keypoints[None], torch.Generator().manual_seed(0), share=1.0)

    def elevation(points, side, names):
        arm = points[..., names.index(f"{side}_wrist"), :] - points[..., names.index(f"{side}_shoulder"), :]
        return arm[..., 1] / arm.norm(dim=-1)

    for side in ("left", "right"):
        assert (elevation(joints[0], side, JOINTS) >= elevation(positions, side, JOINTS) - 1e-6).all()
        forearm = [JOINTS.index(f"{side}_elbow"), JOINTS.index(f"{side}_wrist")]
        torch.testing.assert_close((joints[0, :, forearm[1]] - joints[0, :, forearm[0]]).norm(dim=-1),
                                   (positions[:, forearm[1]] - positions[:, forearm[0]]).norm(dim=-1))
    legs = [JOINTS.index(j) for j in ("left_knee", "right_ankle", "pelvis", "head")]
    assert torch.equal(joints[0, :, legs], positions[:, legs])
    wrist = KEYPOINTS.index("left_wrist")
    torch.testing.assert_close(raised_keypoints[0, :, wrist], joints[0, :, JOINTS.index("left_wrist")], atol=1e-5, rtol=0)


def test_shipped_lifters_lift_a_held_out_subject(mocap):
    """Both shipped lifters on subject 03 (a test subject) filmed by a fixed camera with detector-like
    noise: joints within a body-sized error, the live one frame by frame as lift_sequence gives it."""
    from humotion.capture.lifting import LIVE_WEIGHTS

    motion = to_canonical(load_motion(mocap / "cmu_cyun9601" / "amc" / "03" / "03_01.amc.gz")).resample(30.0)[:60]
    rotations, positions = motion.world()
    keypoints = body_keypoints_3d(rotations, positions, motion.skeleton)
    generator = torch.Generator().manual_seed(3)
    camera = random_camera(generator, torch.cat([keypoints, positions], 1).flatten(0, 1))
    pixels, depth = camera.project(keypoints)
    noisy, confidence = corrupt(pixels, generator, DetectorNoise(), image_size=camera.size, depth=depth)
    local = camera.to_camera(positions)
    truth = (local - local[:, :1]) / motion.skeleton.height()
    live_model = load_lifter(LIVE_WEIGHTS)
    for model in (load_lifter(), live_model):
        lifted = lift_sequence(model, noisy, confidence)
        error_mm = float((lifted - truth).norm(dim=-1).mean()) * motion.skeleton.height() * 1000
        assert error_mm < 150, (model.config.causal, error_mm)
    live = LiveLifter()
    assert live.model.config.causal
    online = torch.stack([live.push(noisy[t], confidence[t]) for t in range(len(noisy))])
    torch.testing.assert_close(online, lift_sequence(live_model, noisy, confidence), atol=1e-5, rtol=0)


def test_loading_another_networks_weights_says_so():
    from humotion.sparse.tracker import DEFAULT_WEIGHTS as SPARSE_WEIGHTS

    with pytest.raises(ValueError, match="holds SparsePoser weights, not Lifter weights"):
        load_lifter(SPARSE_WEIGHTS)


def test_a_person_off_the_optical_axis_is_lifted_as_if_the_camera_looked_at_them(walk, walk_keypoints):
    # One camera position, turned two ways: at the person, and 28 degrees to the side and 16 down,
    # which puts them near the edge of a 90-degree image. Lifted through a perspective crop
    # (person_centred), the second view's joints turned into the first camera's axes are the
    # first view's; the lifter alone, fed the skewed edge-of-image keypoints, strays further.
    from humotion.capture.pipeline import Segment, lift_segment

    lifter = load_lifter()
    frames = slice(0, 90)
    points, pelvis = walk_keypoints[frames], walk.world_positions()[frames, 0].mean(0)
    eye = pelvis + torch.tensor([0.5, 0.6, -4.0])
    turned = torch.tensor([[math.cos(0.49), 0.0, math.sin(0.49)], [0.0, 1.0, 0.0], [-math.sin(0.49), 0.0, math.cos(0.49)]])
    aside = eye + turned @ (pelvis - eye) + torch.tensor([0.0, -1.2, 0.0])
    cameras = [VirtualCamera.looking_at(eye, target, hfov_deg=90.0, width=1280, height=720) for target in (pelvis, aside)]
    lifts = {}
    for name, camera in zip(("at", "aside"), cameras):
        pixels, _ = camera.project(points)
        assert bool(((pixels >= 0) & (pixels <= camera.size)).all())
        segment = Segment(0, torch.arange(len(pixels)), torch.arange(len(pixels)) / 30.0, pixels,
                          torch.ones(pixels.shape[:-1]))
        lifts[name] = (lift_segment(lifter, segment, camera), lift_sequence(lifter, pixels, segment.confidence))
    to_first = cameras[0].rotation @ cameras[1].rotation.T                               # camera 2's axes -> camera 1's
    centre_x = float(cameras[1].project(pelvis)[0][0])
    assert centre_x < 300 or centre_x > 980                                              # near an edge
    cropped, plain = ((lifts["aside"][i] @ to_first.T - lifts["at"][i]).norm(dim=-1).mean() for i in (0, 1))
    assert float(cropped) < 0.02 and float(cropped) < 0.3 * float(plain), (float(cropped), float(plain))


def test_a_frame_with_nothing_seen_does_not_turn_the_perspective_crop(walk_keypoints):
    from humotion.capture.lifting import person_centred

    camera = VirtualCamera.looking_at(torch.tensor([2.0, 1.5, -4.0]), torch.tensor([0.0, 1.0, 0.0]), hfov_deg=70.0,
                                      width=1280, height=720)
    pixels, _ = camera.project(walk_keypoints[:40])
    seen = torch.ones(pixels.shape[:-1])
    _, turns = person_centred(pixels, seen, camera)
    blank = seen.clone()
    blank[20] = 0.0                                   # a frame bridged with nothing detected
    _, turns_blank = person_centred(pixels, blank, camera)
    assert float((turns_blank - turns).abs().max()) < 0.01                  # its neighbours' crops hold
    _, none_seen = person_centred(pixels, torch.zeros_like(seen), camera)
    torch.testing.assert_close(none_seen, torch.eye(3).expand(40, 3, 3))   # no centre, no turn
