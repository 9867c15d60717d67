"""Body-model fitting (humotion.body.fitting) on known answers: bodies of known shape posed by
real CMU mocap (a held-out subject's run, retargeted with pose_from_canonical), their 3D joints
or their detector keypoints seen by a known camera, fitted back with the shipped low-resolution
model."""

import pytest
import torch

from humotion import rotations as rot
from humotion.body.anthropometry import mesh_height
from humotion.body.fitting import (body_points, fit_pose_to_vertices, fit_shape_to_keypoint_frames, fit_to_joints,
                                   fit_to_keypoints, keypoint_vertices)
from humotion.body.model import load_body_model, shipped_weights
from humotion.body.posing import CANONICAL_TO_RIG
from humotion.canonical import to_canonical
from humotion.capture.detection import KEYPOINTS
from humotion.capture.keypoints import VirtualCamera, random_camera
from humotion.io import load_motion

JOINTS = list(CANONICAL_TO_RIG.values())   # the 20 rig joints that canonical (mocap, lifter) joints drive


@pytest.fixture(scope="module")
def low():
    if not shipped_weights("low").exists():
        pytest.skip("no shipped body weights")
    torch.set_num_threads(1)
    return load_body_model("low")


@pytest.fixture(scope="module")
def run(mocap) -> torch.Tensor:
    """(T, 22, 4) canonical rotations of CMU 09_11 (a run; subject 09 is held out of training)."""
    return to_canonical(load_motion(mocap / "cmu_sxaxmz" / "amc" / "09" / "09_11__run.amc.gz")).rotations


def people(low, heights: list[float], seed: int = 0) -> torch.Tensor:
    """(len(heights), shape_latent) shapes from the model's population, each the sample nearest a height (m)."""
    shapes = low.sample_shapes(2000, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        sampled = mesh_height(low.decode_shape(shapes))
    return shapes[[int((sampled - h).abs().argmin()) for h in heights]]


def posed(low, shapes, canonical, translation):
    """Bodies of `shapes` in canonical poses (B, 22, 4), moved by translation (B, 3) m:
    (rig rotations (B, J, 3, 3), BodyOutput)."""
    pose = torch.cat([low.pose_from_canonical(c, shape=s[None]) for c, s in zip(canonical, shapes)])
    with torch.no_grad():
        return pose, low(shape=shapes, pose=pose, translation=translation)


def mm(a, b):
    """(B, K) distances in millimetres."""
    return (a - b).norm(dim=-1) * 1000


def inside_limits(low, pose):
    return float(low.limits.violation(pose).max()) <= 1e-6


# -- points ------------------------------------------------------------------------------------

def test_keypoint_vertices_sit_where_detectors_put_them(low):
    with torch.no_grad():
        out = low(shape=low.shape_latent_mean[None])
    p = dict(zip(KEYPOINTS, body_points(low, out.joints, out.vertices, KEYPOINTS)[0]))
    eye_y, eye_z = p["left_eye"][1], p["left_eye"][2]
    assert abs(float(p["nose"][0])) < 0.01 and p["nose"][2] > eye_z and p["nose"][1] < eye_y   # ahead, below, centred
    assert p["left_ear"][0] > p["left_eye"][0] + 0.02 and p["left_ear"][2] < eye_z - 0.04      # outside, behind the eye
    assert eye_y - 0.06 < p["left_ear"][1] < eye_y
    for side in ("left", "right"):
        heel, ankle, toe = p[f"{side}_heel"], p[f"{side}_ankle"], p[f"{side}_big_toe"]
        assert heel[2] < ankle[2] - 0.03 and heel[1] < ankle[1]                           # behind and below
        assert toe[2] > ankle[2] + 0.12 and abs(float(toe[0])) < abs(float(ankle[0]))      # ahead, towards the midline
    mirrored = {name: p[name.replace("left", "right")] * torch.tensor([-1.0, 1.0, 1.0]) for name in p if "left" in name}
    assert all(torch.allclose(mirrored[name], p[name], atol=2e-3) for name in mirrored)
    assert len(set(keypoint_vertices(low).values())) == 7


# -- 3D ----------------------------------------------------------------------------------------

def test_fit_to_joints_recovers_a_child_and_an_adult(low, run):
    shapes = people(low, [1.15, 1.80])
    translation = torch.tensor([[0.4, 0.1, -0.3], [-1.0, 0.0, 2.0]])
    pose, truth = posed(low, shapes, run[[30, 110]], translation)
    joints = truth.joints[:, [low.joint_names.index(n) for n in JOINTS]]
    fit = fit_to_joints(low, joints, JOINTS)
    assert mm(fit.points, joints).mean(1).max() < 8.0
    assert mm(fit.points, joints).max() < 30.0
    assert mm(fit.vertices, truth.vertices).mean(1).max() < 25.0     # joints leave girths open
    assert (fit.height - mesh_height(truth.rest_vertices)).abs().max() * 100 < 2.5   # cm (head top, soles unseen)
    assert inside_limits(low, fit.pose)
    assert fit.shape.shape == (2, low.config.shape_latent) and fit.translation.shape == (2, 3)


def test_fit_to_joints_with_noise_and_missing_joints(low, run):
    shapes = people(low, [1.65], seed=1)
    _, truth = posed(low, shapes, run[70:71], torch.tensor([[0.0, 0.0, 1.0]]))
    joints = truth.joints[:, [low.joint_names.index(n) for n in JOINTS]]
    noisy = joints + 0.01 * torch.randn(joints.shape, generator=torch.Generator().manual_seed(2))
    missing = [JOINTS.index(n) for n in ("lowerleg01.R", "spine02", "clavicle.L")]   # their neighbours place them
    confidences = torch.ones(1, len(JOINTS)).index_fill(1, torch.tensor(missing), 0.0)
    noisy[:, missing] = float("nan")                         # ignored where the confidence is 0
    fit = fit_to_joints(low, noisy, JOINTS, confidences, noise=0.01)
    error = mm(fit.points, joints)[0]
    assert error.mean() < 20.0 and error[missing].max() < 50.0
    assert abs(float(fit.height - mesh_height(truth.rest_vertices))) * 100 < 3.0


def test_fits_stay_inside_the_joint_limits(low, run):
    """A knee bent backwards past its limit: the fit bends it exactly as far as the limit allows,
    so that leg's ankle misses while the other leg's fits."""
    knee = low.joint_names.index("lowerleg01.L")
    shapes = people(low, [1.70], seed=3)
    canonical_pose, _ = posed(low, shapes, run[50:51], None)
    rotvec = rot.convert(canonical_pose, "matrix", "rotvec")
    lowest = float(low.limits.centre[knee, 0] - low.limits.half_range[knee, 0])
    rotvec[0, knee, 0] = lowest - 0.6                        # hyperextended by 0.6 rad (34 degrees)
    with torch.no_grad():
        truth = low(shape=shapes, pose=rotvec)
    assert float(low.limits.violation(rotvec)[0, knee]) > 0.5
    joints = truth.joints[:, [low.joint_names.index(n) for n in JOINTS]]
    fit = fit_to_joints(low, joints, JOINTS, shape=shapes)
    assert inside_limits(low, fit.pose)
    assert abs(float(fit.pose[0, knee, 0]) - lowest) < 1e-3
    error = mm(fit.points, joints)[0]
    assert error[JOINTS.index("foot.L")] > 30.0 and error[JOINTS.index("foot.R")] < 15.0


# -- 2D ----------------------------------------------------------------------------------------

def keypoints_3d(low, out):
    return body_points(low, out.joints, out.vertices, KEYPOINTS)


def depth_ratio(camera, fitted, true):
    """(B,) fitted / true depth of the root joints (B, 3) along the optical axis."""
    return camera.to_camera(fitted)[..., 2] / camera.to_camera(true)[..., 2]


TRUNK = [KEYPOINTS.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")]


def trunk_error(fit, points, truth):
    """(B,) mean error (mm) of the shoulders and hips relative to the root joint. One view leaves
    each limb's depth open (a leg swung forward or back looks alike), so limbs are judged in 2D."""
    return mm(fit.points - fit.joints[:, :1], points - truth.joints[:, :1])[:, TRUNK].mean(1)


def test_fit_to_keypoints_with_the_shape_known(low, run):
    """Five frames of a run: one view leaves local minima, so a frame may land a few px off (the
    median is what the fit promises; each frame stays within 8 px)."""
    frames = [30, 60, 90, 120, 150]
    shapes = people(low, [1.75], seed=4).expand(len(frames), -1)
    _, truth = posed(low, shapes, run[frames], torch.tensor([[0.3, 0.0, -0.5]]).expand(len(frames), -1))
    camera = VirtualCamera.looking_at([1.5, 1.2, 4.0], [0.0, 0.0, 0.0], 60.0, 1280, 720)
    points = keypoints_3d(low, truth)
    pixels, _ = camera.project(points)
    fit = fit_to_keypoints(low, pixels, torch.ones(len(frames), 21), camera, shape=shapes, noise=0.1)
    reprojection = (camera.project(fit.points)[0] - pixels).norm(dim=-1).mean(-1)        # px, of ~400
    assert reprojection.median() < 2.5 and reprojection.max() < 8.0
    assert trunk_error(fit, points, truth).median() < 120.0
    assert (depth_ratio(camera, fit.joints[:, 0], truth.joints[:, 0]) - 1).abs().median() < 0.03
    assert inside_limits(low, fit.pose)


def test_fit_to_keypoints_with_pixel_noise_and_dropped_keypoints(low, run):
    """Two people, each filmed by their own random camera; 2 px noise, four keypoints dropped.
    The second person's trunk error swings between about 45 and 121 mm when its keypoints move by
    1 micrometre (measured over seven such perturbations): one view leaves the depth of the
    shoulders and hips about the root ambiguous, and the fit settles in one minimum or another.
    The bound allows for that."""
    generator = torch.Generator().manual_seed(5)
    shapes = people(low, [1.60, 1.85], seed=5)
    _, truth = posed(low, shapes, run[[20, 140]], torch.zeros(2, 3))
    points = keypoints_3d(low, truth)
    camera = random_camera(generator, points)
    pixels, _ = camera.project(points)
    noisy = pixels + 2.0 * torch.randn(pixels.shape, generator=generator)
    dropped = torch.tensor([KEYPOINTS.index(n) for n in ("nose", "left_ear", "right_hip", "left_big_toe")])
    confidences = torch.ones(2, 21).index_fill(1, dropped, 0.0)
    noisy[:, dropped] = float("nan")
    fit = fit_to_keypoints(low, noisy, confidences, camera, shape=shapes, noise=0.1)
    reprojected = (camera.project(fit.points)[0] - pixels).norm(dim=-1)
    seen = confidences[0] > 0
    assert reprojected[:, seen].mean() < 4.0 and reprojected[:, ~seen].mean() < 15.0
    assert trunk_error(fit, points, truth).max() < 150.0
    assert (depth_ratio(camera, fit.joints[:, 0], truth.joints[:, 0]) - 1).abs().max() < 0.05
    assert inside_limits(low, fit.pose)


def test_fit_to_keypoints_fixes_the_shape_up_to_scale(low, run):
    """With the shape free, one view gives proportions, not size: the fitted body's height over
    its distance is the true one, whatever the height."""
    shapes = people(low, [1.50], seed=6)
    _, truth = posed(low, shapes, run[60:61], torch.tensor([[0.0, 0.0, -1.0]]))
    camera = VirtualCamera.looking_at([-2.0, 1.0, 3.0], [0.0, 0.0, -1.0], 60.0, 1280, 720)
    pixels, _ = camera.project(keypoints_3d(low, truth))
    fit = fit_to_keypoints(low, pixels, torch.ones(1, 21), camera, noise=0.1)
    assert (camera.project(fit.points)[0] - pixels).norm(dim=-1).mean() < 3.5
    size_over_depth = fit.height / mesh_height(truth.rest_vertices) / depth_ratio(camera, fit.joints[:, 0],
                                                                                   truth.joints[:, 0])
    assert abs(float(size_over_depth) - 1) < 0.05


def test_fit_shape_to_keypoint_frames_shares_one_shape(low, run):
    """Eight frames of a run seen by one camera, exact keypoints: one shape for all frames, a pose
    per frame; the frames fit and the height comes out near the true one."""
    shapes = people(low, [1.70], seed=9)
    frames = run[10:130:15]
    _, truth = posed(low, shapes.expand(len(frames), -1), frames, torch.zeros(len(frames), 3))
    camera = VirtualCamera.looking_at([2.0, 1.3, 4.5], [0.0, 0.9, 0.0], 60.0, 1280, 720)
    pixels, _ = camera.project(keypoints_3d(low, truth))
    fit = fit_shape_to_keypoint_frames(low, pixels, torch.ones(len(frames), 21), camera, noise=0.3)
    assert fit.shape.shape == (len(frames), low.config.shape_latent) and torch.equal(fit.shape[0], fit.shape[-1])
    assert (camera.project(fit.points)[0] - pixels).norm(dim=-1).mean() < 4.0                  # px
    assert abs(float(fit.height[0] - mesh_height(truth.rest_vertices[:1]))) * 100 < 8.0       # cm
    assert inside_limits(low, fit.pose)


# -- inputs and the training-time pose fit -----------------------------------------------------

def test_inputs_are_checked(low):
    joints = torch.zeros(1, len(JOINTS), 3)
    camera = VirtualCamera.looking_at([0.0, 1.0, 4.0], [0.0, 1.0, 0.0], 60.0, 640, 480)
    with pytest.raises(ValueError, match="unknown point 'tail'"):
        fit_to_joints(low, joints, JOINTS[:-1] + ["tail"])
    with pytest.raises(ValueError, match=r"\(B, 20, 3\)"):
        fit_to_joints(low, joints[..., :2], JOINTS)
    with pytest.raises(ValueError, match="NaN"):
        fit_to_joints(low, torch.full_like(joints, float("nan")), JOINTS)
    with pytest.raises(ValueError, match="3 or more"):
        fit_to_joints(low, joints, JOINTS, torch.zeros(1, len(JOINTS)).index_fill(1, torch.tensor([0, 1]), 1.0))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        fit_to_keypoints(low, torch.zeros(21, 2), torch.full((21,), 2.0), camera)
    with pytest.raises(ValueError, match=r"\(B, 21, 2\)"):
        fit_to_keypoints(low, torch.zeros(17, 2), torch.ones(17), camera)
    with pytest.raises(ValueError, match=r"confidences must be \(1, 20\) or \(20,\)"):
        fit_to_joints(low, joints, JOINTS, torch.ones(7))
    with pytest.raises(ValueError, match="noise must be a positive number"):
        fit_to_joints(low, joints, JOINTS, noise=0.0)
    with pytest.raises(ValueError, match="pose_sigma must be a positive number"):
        fit_to_keypoints(low, torch.zeros(21, 2), torch.ones(21), camera, pose_sigma=-1.0)


def test_fit_pose_to_vertices_recovers_a_perturbed_pose(low, run):
    shapes = people(low, [1.70], seed=7)
    pose, truth = posed(low, shapes, run[100:101], torch.zeros(1, 3))
    free = low.limits.to_free(rot.convert(pose, "matrix", "rotvec"))
    moving = low.limits.half_range > 0
    start = free + 0.05 * torch.randn(free.shape, generator=torch.Generator().manual_seed(8)) * moving
    _, _, before, after = fit_pose_to_vertices(low, truth.vertices, truth.rest_vertices, start, torch.zeros(1, 3))
    assert float(before) > 20.0 and float(after) < float(before) / 3                      # mm
