"""Capture refinement (E_key + E_init + E_prior + E_temporal) and the Gaussian pose prior,
on real CMU motion filmed by a known virtual camera."""

import math

import numpy as np
import pytest
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS, to_canonical
from humotion.capture.camera import SOLES
from humotion.capture.joint_angles import correct_bone_lengths, positions_to_rotations
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d
from humotion.capture.prior import PosePrior, fit_pose_prior
from humotion.capture.refine import CaptureRefineConfig, initial_root, intrinsics, refine_capture, second_differences
from humotion.capture.template import template_skeleton
from humotion.io import load_motion
from humotion.skeleton import forward_kinematics


def walk_of_subject_07(mocap):
    return mocap / "cmu_visdoom_mocapplayer" / "amc" / "07_01-walk.amc"


@pytest.fixture(scope="module")
def prior(mocap):
    """Fitted on two subjects' jumps, walks and punches (01, 02); the test poses come from subject 07."""
    takes = [to_canonical(load_motion(mocap / path)).resample(30.0)
             for path in ("cmu_fairmotion/01_01.bvh", "cmu_mocgui_s02/02_01.amc", "cmu_mocgui_s02/02_05.amc")]
    rotations = torch.cat([m.rotations for m in takes] + [m.mirrored().rotations for m in takes])
    return fit_pose_prior(rotations)


@pytest.fixture(scope="module")
def scene(mocap):
    """A 2 s walk of another subject on the 1.65 m template, 4 m in front of a 640x480 camera,
    everything in the camera frame: (true rotvecs, true root, skeleton, camera, pixels)."""
    motion = to_canonical(load_motion(walk_of_subject_07(mocap))).resample(30.0)[30:90]
    skeleton = template_skeleton()
    centre = motion.root_positions.mean(0)
    camera = VirtualCamera.looking_at(centre + torch.tensor([0.0, 0.3, 4.0]), centre, 60.0, 640, 480)
    to_camera = camera.rotation
    rotations = rot.quat_to_matrix(motion.rotations).clone()
    rotations[:, 0] = to_camera @ rotations[:, 0]
    root = camera.to_camera(motion.root_positions)
    rotvecs = rot.convert(rotations, "matrix", "rotvec")
    world_r, joints = forward_kinematics(rotations, root, skeleton.offsets, skeleton.parents)
    pixels, depth = intrinsics(camera).project(body_keypoints_3d(world_r, joints, skeleton))
    assert (depth > 2).all() and (pixels >= 0).all() and (pixels[..., 0] <= 640).all() and (pixels[..., 1] <= 480).all()
    return rotvecs, root, skeleton, camera, pixels


def test_prior_prefers_real_poses_to_broken_ones(prior, mocap):
    held_out = to_canonical(load_motion(walk_of_subject_07(mocap))).resample(30.0)
    rotvecs = rot.convert(held_out.rotations, "quat", "rotvec")
    real = prior.energy(rotvecs)
    assert prior.energy(prior.mean.view(21, 3).new_zeros(1, 22, 3) + torch.cat([torch.zeros(1, 3), prior.mean.view(21, 3)])[None]).item() == pytest.approx(0, abs=1e-3)
    broken = rotvecs.clone()
    knee = JOINTS.index("left_knee")
    broken[:, knee] = torch.tensor([-math.radians(60), 0.0, 0.0])    # bent forwards, the wrong way
    assert (prior.energy(broken) > prior.energy(rotvecs)).float().mean() > 0.95
    assert real.median() < 0.5 * prior.energy(broken).median()
    with pytest.raises(ValueError, match="22, 3"):
        prior.energy(torch.zeros(5, 21, 3))


def test_shipped_prior_knows_a_held_out_subject(mocap):
    shipped = PosePrior.load()
    assert shipped.frames > 10000
    held_out = rot.convert(to_canonical(load_motion(walk_of_subject_07(mocap))).rotations, "quat", "rotvec")
    broken = held_out.clone()
    broken[:, JOINTS.index("right_elbow")] = torch.tensor([0.0, 0.0, math.radians(-90)])  # a 90-degree bend about an axis elbows do not bend about
    assert shipped.energy(held_out).median() < 0.25 * shipped.energy(broken).median()


def test_prior_file_round_trip(prior, tmp_path):
    prior.save(tmp_path / "prior.npz")
    loaded = PosePrior.load(tmp_path / "prior.npz")
    assert torch.equal(loaded.mean, prior.mean) and torch.equal(loaded.precision, prior.precision)
    with pytest.raises(FileNotFoundError, match="humotion train prior"):
        PosePrior.load(tmp_path / "missing.npz")


def test_initial_root_recovers_the_translation_from_pixels_alone(scene):
    rotvecs, root, skeleton, camera, pixels = scene
    world_r, joints = forward_kinematics(rot.convert(rotvecs, "rotvec", "matrix"), torch.zeros_like(root),
                                         skeleton.offsets, skeleton.parents)
    relative = body_keypoints_3d(world_r, joints, skeleton)
    confidence = torch.ones(pixels.shape[:2])
    confidence[:, :5] = 0      # the face unseen
    found = initial_root(relative, pixels + 1000 * (confidence == 0)[..., None], confidence, camera)
    assert (found - root).norm(dim=-1).max() < 1e-3


def test_second_differences_are_exact_on_a_parabola_with_unequal_steps():
    times = np.array([0.0, 0.1, 0.15, 0.3, 0.32, 0.5])
    assert np.allclose(second_differences(times) @ (3 * times**2 - times + 2), 6.0)


def test_a_root_track_from_timestamps_keeps_a_far_walker_steady_in_depth(scene):
    """The walk 12 m away with 1 px of detector noise: the per-frame root jumps in depth by
    tens of centimetres between frames (its speed, not a person's); solved over the track with
    the acceleration prior, it moves as the walker does and is closer to the truth."""
    rotvecs, root, skeleton, camera, _ = scene
    far = root + torch.tensor([0.0, 0.0, 8.0])
    world_r, joints = forward_kinematics(rot.convert(rotvecs, "rotvec", "matrix"), torch.zeros_like(root),
                                         skeleton.offsets, skeleton.parents)
    relative = body_keypoints_3d(world_r, joints, skeleton)
    pixels, _ = intrinsics(camera).project(relative + far[:, None])
    pixels = pixels + torch.randn(pixels.shape, generator=torch.Generator().manual_seed(0))
    confidence = torch.ones(pixels.shape[:2])
    confidence[20:23] = 0                                              # a detection lost for 3 frames
    times = np.arange(len(root)) / 30.0
    per_frame = initial_root(relative, pixels, confidence, camera)
    track = initial_root(relative, pixels, confidence, camera, times)
    true_speed = far.diff(dim=0).norm(dim=-1) * 30

    def speed_error(found):
        return float(((found.diff(dim=0).norm(dim=-1) * 30) - true_speed).abs().median())

    assert speed_error(per_frame) > 1.0 and speed_error(track) < 0.2      # m/s
    assert (track - far).norm(dim=-1).median() < 0.75 * (per_frame - far).norm(dim=-1)[confidence[:, 0] > 0].median()
    assert (track[20:23] - far[20:23]).norm(dim=-1).max() < 0.2           # bridged where nothing was seen
    repeated = times.copy()
    repeated[10] = repeated[9]                                         # a glitched timestamp: solved per frame
    assert torch.equal(initial_root(relative, pixels, confidence, camera, repeated), per_frame)


def test_refinement_beats_the_noisy_network(scene, prior):
    rotvecs, root, skeleton, camera, pixels = scene
    g = torch.Generator().manual_seed(0)
    rotations = rot.convert(rotvecs, "rotvec", "matrix")
    _, true_joints = forward_kinematics(rotations, root, skeleton.offsets, skeleton.parents)
    true_relative = true_joints - root[:, None]
    # The "network": 4 cm of independent noise per joint and frame; the detector: 3 px.
    network = correct_bone_lengths(true_relative + 0.04 * torch.randn(true_relative.shape, generator=g), skeleton)
    detected = pixels + 3.0 * torch.randn(pixels.shape, generator=g)
    confidence = torch.full(pixels.shape[:2], 0.9)
    start_q, _ = positions_to_rotations(network, skeleton)
    start = rot.convert(start_q, "quat", "rotvec")
    world_r, joints = forward_kinematics(start_q, torch.zeros_like(root), skeleton.offsets, skeleton.parents)
    start_root = initial_root(body_keypoints_3d(world_r, joints, skeleton), detected, confidence, camera)

    def errors(theta, r):
        world_r, joints = forward_kinematics(rot.convert(theta, "rotvec", "matrix"), r, skeleton.offsets, skeleton.parents)
        mpjpe = (joints - true_joints).norm(dim=-1).mean()
        accel = (joints.diff(n=2, dim=0) - true_joints.diff(n=2, dim=0)).norm(dim=-1).mean()
        return float(mpjpe), float(accel)

    before = errors(start, start_root)
    theta, r = refine_capture(start, start_root, skeleton, camera, detected, confidence, network, prior)
    after = errors(theta, r)
    assert after[0] < 0.8 * before[0], (before, after)          # closer to the truth
    assert after[1] < 0.5 * before[1], (before, after)          # far less jitter
    # Without the temporal term the jitter stays.
    theta2, r2 = refine_capture(start, start_root, skeleton, camera, detected, confidence, network, prior,
                                CaptureRefineConfig().without("temporal"))
    assert errors(theta2, r2)[1] > 1.5 * after[1]
    with pytest.raises(ValueError, match="unknown refinement term"):
        CaptureRefineConfig().without("gravity")


def test_the_body_lands_on_its_own_keypoints_despite_a_biased_network_and_outliers(scene, prior):
    """The network leans the whole body 12 degrees (the lifter's systematic errors are of this
    kind); the detector has 1 px of noise and 2% gross outliers. The refinement's E_key outweighs
    the closeness to the network, and its robust loss ignores the outliers: the body's keypoints
    land on the good detections within a few pixels, where the old weights (E_key 1, plain
    squares) left most of the lean's error."""
    rotvecs, root, skeleton, camera, pixels = scene
    g = torch.Generator().manual_seed(1)
    rotations = rot.convert(rotvecs, "rotvec", "matrix")
    _, true_joints = forward_kinematics(rotations, root, skeleton.offsets, skeleton.parents)
    lean = rot.convert(torch.tensor([math.radians(12.0), 0.0, 0.0]), "rotvec", "matrix")
    network = correct_bone_lengths((true_joints - root[:, None]) @ lean.T, skeleton)
    detected = pixels + torch.randn(pixels.shape, generator=g)
    outliers = torch.rand(pixels.shape[:2], generator=g) < 0.02
    detected[outliers] += 80.0 * torch.randn(int(outliers.sum()), 2, generator=g)
    confidence = torch.full(pixels.shape[:2], 0.6)
    start_q, _ = positions_to_rotations(network, skeleton)
    world_r, joints = forward_kinematics(start_q, torch.zeros_like(root), skeleton.offsets, skeleton.parents)
    start_root = initial_root(body_keypoints_3d(world_r, joints, skeleton), detected, confidence, camera)
    start = rot.convert(start_q, "quat", "rotvec")

    def pixel_error(theta, r):
        world_r, joints = forward_kinematics(rot.convert(theta, "rotvec", "matrix"), r, skeleton.offsets, skeleton.parents)
        projected, _ = intrinsics(camera).project(body_keypoints_3d(world_r, joints, skeleton))
        return float((projected - pixels).norm(dim=-1)[~outliers].median())

    now = pixel_error(*refine_capture(start, start_root, skeleton, camera, detected, confidence, network, prior))
    old = CaptureRefineConfig(key=1.0, robust=0.0, temporal=1.0)
    before = pixel_error(*refine_capture(start, start_root, skeleton, camera, detected, confidence, network, prior, old))
    print(f"median px off the true keypoints: start {pixel_error(start, start_root):.1f}, old weights {before:.1f}, now {now:.1f}")
    assert now < 3.0 and now < 0.5 * before, (now, before)


def test_support_holds_a_body_on_the_floor_where_no_sole_is_found_planted(scene, prior):
    """Detections of the walk floating 15 cm over its floor, and no sole planted: E_floor and
    E_skate have nothing to hold, E_key keeps the body up; E_support brings every frame's lowest
    sole down to the floor (fails without it: the soles stay about 15 cm up)."""
    rotvecs, root, skeleton, camera, _ = scene
    up = camera.to_camera(torch.tensor([[0.0, 1.0, 0.0]]))[0] - camera.to_camera(torch.zeros(1, 3))[0]
    lifted = root + 0.15 * up
    world_r, joints = forward_kinematics(rot.convert(rotvecs, "rotvec", "matrix"), torch.zeros_like(root),
                                         skeleton.offsets, skeleton.parents)
    relative = body_keypoints_3d(world_r, joints, skeleton)
    height = -float(((relative + root[:, None])[:, SOLES] @ up).min())        # the walk's own floor
    pixels, _ = intrinsics(camera).project(relative + lifted[:, None])
    confidence = torch.ones(pixels.shape[:2])
    network = joints - joints[:, :1]
    lowest = {}
    for support in (0.0, CaptureRefineConfig().support):
        theta, r = refine_capture(rotvecs, lifted, skeleton, camera, pixels, confidence, network, prior,
                                  CaptureRefineConfig(support=support), floor=(up, height))
        world_r, joints = forward_kinematics(rot.convert(theta, "rotvec", "matrix"), r, skeleton.offsets,
                                             skeleton.parents)
        lowest[support] = (body_keypoints_3d(world_r, joints, skeleton)[:, SOLES] @ up + height).amin(1)
    assert lowest[0.0].median() > 0.1
    assert lowest[CaptureRefineConfig().support].abs().quantile(0.9) < 0.03


def test_the_compiled_energy_and_gradient_match_autograd(scene, prior):
    """humotion.capture.refine_energy (numba, gradient by hand) against the energy written in torch
    (Terms.energy) and differentiated by autograd, in float64, on a noisy walk with every term on:
    soles planted, held, under the floor and above it, an upright joint (rotation vector 0: the
    series branch). Fails on a sign slip in any term's gradient."""
    from humotion.capture.refine import SUPPORT_TOLERANCE, Terms, person_size

    rotvecs, root, skeleton, camera, pixels = scene
    g = torch.Generator().manual_seed(2)
    theta = rotvecs.double() + 0.05 * torch.randn(rotvecs.shape, generator=g, dtype=torch.float64)
    theta[:, 3] = 0.0
    r = root.double() + 0.02 * torch.randn(root.shape, generator=g, dtype=torch.float64)
    detected = pixels.double() + 2.0 * torch.randn(pixels.shape, generator=g, dtype=torch.float64)
    confidence = torch.rand(pixels.shape[:2], generator=g, dtype=torch.float64)
    network = 0.03 * torch.randn(len(r), len(JOINTS), 3, generator=g, dtype=torch.float64)
    up = torch.tensor([0.05, -0.98, 0.2], dtype=torch.float64)
    up = up / up.norm()
    world_r, joints = forward_kinematics(rot.convert(theta, "rotvec", "matrix"), r, skeleton.offsets.double(), skeleton.parents)
    soles = body_keypoints_3d(world_r, joints, skeleton)[:, SOLES] @ up
    height = -float(soles.amin(1).median())                                       # a floor tilted against the walk's
    assert (soles + height < 0).any() and (soles.amin(1) + height > SUPPORT_TOLERANCE).any()   # both floor terms pull
    planted = (torch.rand(len(r), 4, generator=g) < 0.5).double()
    held = (torch.rand(len(r) - 1, 4, generator=g) < 0.5).double()
    prior64 = PosePrior(prior.mean.double(), prior.precision.double(), prior.frames)
    terms = Terms(skeleton, camera, detected, confidence, person_size(detected, confidence), network, prior64,
                  CaptureRefineConfig(), up, height, True, planted, held)

    variables = [theta.clone().requires_grad_(True), r.clone().requires_grad_(True)]
    expected = terms.energy(*variables)
    expected_gradients = torch.autograd.grad(expected, variables)
    value, gradients = terms.compiled(theta, r)()
    assert value == pytest.approx(float(expected.detach()), rel=1e-9)
    for found, wanted in zip(gradients, expected_gradients):
        assert torch.allclose(found, wanted, rtol=1e-6, atol=1e-6 * float(wanted.abs().max())), \
            float((found - wanted).abs().max())
