"""The capture pipeline end to end on real photos made into a video: files, JSON, constant bones,
partial results and clear errors. The lifter here is small and untrained (the plumbing is under
test; accuracy is bench/capture_eval.py's job)."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from humotion.canonical import JOINTS
from humotion.capture.lifting import Lifter, LiftingConfig
from humotion.capture.pipeline import CaptureConfig, capture
from humotion.capture.refine import CaptureRefineConfig
from humotion.capture.template import bone_lengths, template_skeleton
from humotion.io import load_motion
from humotion.io.errors import MotionFileError
from humotion.io.video import VideoWriter, open_frames

PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "images" / "yogait_cc0"


@pytest.fixture(scope="module")
def lifter():
    torch.manual_seed(0)
    return Lifter(LiftingConfig(channels=16, levels=2)).eval()


@pytest.fixture(scope="module")
def detector():
    from humotion.capture.detection import MediaPipePoseDetector

    with MediaPipePoseDetector(max_people=2) as found:
        yield found


def photo(name: str, width: int = 400) -> np.ndarray:
    if not (PHOTOS / name).is_file():
        pytest.skip(f"test photos not found at {PHOTOS}")
    image = cv2.cvtColor(cv2.imread(str(PHOTOS / name)), cv2.COLOR_BGR2RGB)
    return cv2.resize(image, (width, round(image.shape[0] * width / image.shape[1])))


def video_of(frames: list[np.ndarray], path: Path) -> Path:
    with VideoWriter(path, fps=30.0) as writer:
        for frame in frames:
            writer.write(frame)
    return path


def quick() -> CaptureConfig:
    return CaptureConfig(refine=CaptureRefineConfig(iterations=5, photo_iterations=5))


def test_one_person_video_gives_files_json_and_constant_bones(tmp_path, lifter, detector):
    still = photo("tadasana_tada1.jpg")
    frames = [np.roll(still, 2 * k, axis=1) for k in range(6)]       # the person moves right, 2 px a frame
    source = video_of(frames, tmp_path / "walk.mp4")
    result = capture(source, tmp_path / "out", quick(), detector=detector, lifter=lifter, progress=False)
    # the untrained lifter's people do not stand: the camera is taken as level, with a warning; the
    # whole image moving 2 px a frame reads as a panning camera, with another
    assert len(result.people) == 1 and all("level" in w or "moving camera" in w for w in result.warnings)
    person = result.people[0]
    names = {p.name for p in result.files}
    assert {f"person{person.segment.person}.bvh", f"person{person.segment.person}.glb", "capture.json",
            "overlay.mp4"} <= names
    data = json.loads((tmp_path / "out" / "capture.json").read_text())
    frames_out = data["people"][str(person.segment.person)]
    assert [f["frame"] for f in frames_out] == list(range(6))
    assert set(frames_out[0]["keypoints_2d"]) >= {"nose", "left_shoulder", "right_ankle", "left_big_toe"}
    x, y, confidence = frames_out[0]["keypoints_2d"]["left_shoulder"]
    assert 0 <= x <= still.shape[1] and 0 <= y <= still.shape[0] and confidence > 0.5
    assert len(frames_out[0]["joints_3d"]) == 22 and "left_wrist" in frames_out[0]["joints_3d"]
    # The BVH on disk is the 1.65 m template's skeleton, and the JSON's 3D joints keep its bones.
    motion = load_motion(tmp_path / "out" / f"person{person.segment.person}.bvh")
    template = template_skeleton(1.65)
    order = [motion.skeleton.names.index(name) for name in template.names]      # BVH keeps its own joint order
    assert motion.num_frames == 6 and np.allclose(motion.skeleton.offsets[order][1:], template.offsets[1:], atol=1e-5)
    joints = torch.tensor([[f["joints_3d"][name] for name in JOINTS] for f in frames_out])
    expected = torch.as_tensor(np.linalg.norm(template.offsets, axis=1), dtype=torch.float32)
    torch.testing.assert_close(bone_lengths(joints)[:, 1:], expected[1:].expand(6, -1), atol=2e-4, rtol=0)
    # one camera for everyone, stated in full (the floor under real people: tests/test_capture_feet.py)
    assert set(data["camera"]) >= {"fx", "cx", "rotation_world_to_camera", "position_m", "pitch_deg", "height_m"}
    assert data["reprojection_px"]["points"] > 0 and data["interrupted"] is None
    assert data["camera"]["assumption"].startswith("static") and "rotation_world_to_camera" in data["camera"]
    with open_frames(tmp_path / "out" / "overlay.mp4") as overlay:
        assert len(list(overlay)) == 6


def test_nobody_in_view_keeps_going_and_says_so(tmp_path, lifter, detector, capfd):
    """The warning is returned, not printed (the command prints it)."""
    grey = np.full((240, 320, 3), 128, np.uint8)
    result = capture(video_of([grey] * 4, tmp_path / "empty_room.mp4"), tmp_path / "out", quick(), detector=detector,
                     lifter=lifter, progress=False)
    assert result.people == [] and result.warnings == ["nobody was found"]
    assert "nobody was found" not in capfd.readouterr().err
    assert json.loads((tmp_path / "out" / "capture.json").read_text())["people"] == {}


def test_unreadable_sources_are_named(tmp_path, lifter, detector):
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(MotionFileError, match="empty.mp4"):
        capture(empty, tmp_path / "out", quick(), detector=detector, lifter=lifter, progress=False)


@pytest.mark.parametrize("name", ["t_pose_t6.jpg", "t_pose_t_pose_test.png"])
def test_a_t_pose_photo_gives_level_arms_in_3d(tmp_path, detector, name):
    """The shipped lifter and refinement on a real photo: both arms (shoulder to wrist) within 25
    degrees of horizontal (in these photos the arms themselves sag up to 10 degrees)."""
    result = capture(PHOTOS / name if (PHOTOS / name).is_file() else pytest.skip("photos missing"), tmp_path,
                     detector=detector, progress=False)
    assert len(result.people) == 1
    joints = result.people[0].joints[0]
    for side in ("left", "right"):
        arm = joints[JOINTS.index(f"{side}_wrist")] - joints[JOINTS.index(f"{side}_shoulder")]
        elevation = float(torch.rad2deg(torch.asin(arm[1] / arm.norm())))
        assert abs(elevation) < 25, (side, elevation)


def test_body_option_puts_each_person_on_a_body_of_their_height(tmp_path, detector):
    """CaptureConfig.body: the T-pose photo's person also comes as the learned body model at the
    stated height, in the captured pose (arms level on the body's 76-joint rig too)."""
    import pygltflib

    name = "t_pose_t6.jpg"
    source = PHOTOS / name if (PHOTOS / name).is_file() else pytest.skip("photos missing")
    result = capture(source, tmp_path, CaptureConfig(height_m=1.80, body="low"), detector=detector, progress=False)
    path = tmp_path / "person0_body.glb"
    assert path in result.files and not result.warnings
    facts = pygltflib.GLTF2().load(str(path)).meshes[0].extras["humotion_body"]
    assert facts["height_m"] == pytest.approx(1.80, abs=0.01)
    rig = load_motion(path)
    assert rig.skeleton.num_joints == 76
    joints = rig.world_positions()[0]
    for side in ("L", "R"):
        arm = joints[rig.skeleton.index(f"wrist.{side}")] - joints[rig.skeleton.index(f"upperarm01.{side}")]
        assert abs(float(torch.rad2deg(torch.asin(arm[1] / arm.norm())))) < 25
    with pytest.raises(ValueError, match="body"):
        CaptureConfig(body="medium")


@pytest.mark.parametrize("name", ["tadasana_tada1.jpg", "tadasana_tada3.jpg", "tadasana_tada4.jpg"])
def test_standing_photos_give_upright_bodies_with_feet_below_hips(tmp_path, detector, name):
    result = capture(PHOTOS / name if (PHOTOS / name).is_file() else pytest.skip("photos missing"), tmp_path,
                     detector=detector, progress=False)
    joints = result.people[0].joints[0]
    spine = joints[JOINTS.index("neck")] - joints[JOINTS.index("pelvis")]
    assert float(torch.rad2deg(torch.acos(spine[1] / spine.norm()))) < 5           # the trunk within 5 deg of vertical
    for side in ("left", "right"):
        hip, knee, ankle = (joints[JOINTS.index(f"{side}_{j}"), 1] for j in ("hip", "knee", "ankle"))
        assert ankle < knee < hip


def test_frames_without_a_confident_keypoint_are_left_out():
    from humotion.capture.pipeline import segments_of

    sure, unsure = np.full(21, 0.9, np.float32), np.full(21, 0.05, np.float32)
    points = np.zeros((21, 2), np.float32)
    observations = [(t, t / 30, points, unsure if 3 <= t < 13 else sure) for t in range(18)]   # 0.33 s unsure
    segments = segments_of(7, observations, min_frames=2)
    assert [s.frames.tolist() for s in segments] == [[0, 1, 2], [13, 14, 15, 16, 17]]
    assert segments_of(7, [(t, 0.0, points, unsure) for t in range(5)], min_frames=1) == []


def test_a_segment_holds_tensors_and_refuses_bad_shapes():
    from humotion.capture.pipeline import Segment

    segment = Segment(0, np.arange(3), np.arange(3) / 30, np.zeros((3, 21, 2)), np.ones((3, 21)))
    assert [v.dtype for v in (segment.frames, segment.times, segment.keypoints, segment.confidence)] == \
        [torch.int64, torch.float64, torch.float32, torch.float32]
    long_video = Segment(0, [0], [3600.0 + 1 / 30], torch.zeros(1, 21, 2), torch.ones(1, 21))
    assert float(long_video.times[0]) == 3600.0 + 1 / 30                      # float64: no rounding to float32
    with pytest.raises(ValueError, match=r"keypoints has shape \(3, 17, 2\), expected \(3, 21, 2\)"):
        Segment(0, np.arange(3), np.arange(3) / 30, np.zeros((3, 17, 2)), np.ones((3, 21)))
    with pytest.raises(ValueError, match="times has shape"):
        Segment(0, np.arange(3), np.arange(4) / 30, np.zeros((3, 21, 2)), np.ones((3, 21)))


def test_a_person_missed_for_a_moment_keeps_one_segment_with_the_gap_filled_in():
    from humotion.capture.pipeline import BRIDGED_GAP, segments_of

    confidence = np.full(21, 0.8, np.float32)
    seen = [t for t in range(20) if not 5 <= t < 9]                        # missed on 4 frames (0.13 s at 30 fps)
    observations = [(t, t / 30, np.full((21, 2), 10.0 * t, np.float32), confidence) for t in seen]
    (segment,) = segments_of(3, observations, min_frames=3)
    assert segment.frames.tolist() == list(range(20))
    np.testing.assert_allclose(segment.keypoints[5:9, :, 0], np.repeat([[50.0], [60.0], [70.0], [80.0]], 21, 1))
    np.testing.assert_allclose(segment.times[5:9], np.arange(5, 9) / 30)
    assert (segment.confidence[5:9] == 0.4).all() and (segment.confidence[9] == 0.8).all()
    slow = [(t, t / 10, points, sure) for t, _, points, sure in observations]   # the same frames at 10 fps: 0.5 s
    assert 0.5 > BRIDGED_GAP and [s.frames.tolist() for s in segments_of(3, slow, 3)] == [[0, 1, 2, 3, 4],
                                                                                          list(range(9, 20))]


def test_a_live_source_without_a_length_is_tracked(detector):
    """A camera has no frame count (len raises): the progress bar must not ask for one."""
    from humotion.capture.people import PeopleTracker
    from humotion.capture.pipeline import track_video
    from humotion.io.video import Frame

    still = photo("tadasana_tada1.jpg")

    class Camera:
        live, fps, size, frame_count = True, 30.0, (still.shape[1], still.shape[0]), None

        def __len__(self):
            raise TypeError("camera 0: a live camera has no length")

        def __iter__(self):
            return iter(Frame(k, k / 30, still) for k in range(3))

    tracked = track_video(Camera(), detector, PeopleTracker(), None, progress=True)
    assert tracked.frames == 3 and len(tracked.people) == 1 and not tracked.warnings


def test_a_truncated_video_keeps_the_frames_before_the_damage(tmp_path, lifter, detector):
    still = photo("tadasana_tada1.jpg", width=240)
    whole = tmp_path / "whole.avi"
    with VideoWriter(whole, fps=30.0, codec="mjpeg") as writer:
        for k in range(24):
            writer.write(np.roll(still, k, axis=1))
    cut = tmp_path / "cut.avi"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    result = capture(cut, tmp_path / "out", quick(), detector=detector, lifter=lifter, progress=False)
    # the untrained lifter's people do not stand; the rolled image reads as a panning camera
    warnings = [w for w in result.warnings if "level" not in w and "moving camera" not in w]
    assert len(warnings) == 1 and "ended after" in warnings[0] and "cut.avi" in warnings[0]
    frames = result.people[0].segment.frames
    assert 3 <= len(frames) < 24 and frames[0] == 0
    assert (tmp_path / "out" / "capture.json").is_file()


def test_live_view_follows_the_video_and_the_files_are_still_written(tmp_path, lifter, detector):
    from humotion.viewer.live import LiveView

    still = photo("tadasana_tada1.jpg")
    source = video_of([still] * 3 + [np.zeros_like(still)] + [still] * 3, tmp_path / "blink.mp4")   # gone on frame 3
    view = LiveView(port=0)
    shown = []
    original = view.show
    view.show = lambda people, image: (shown.append(set(people)), original(people, image))
    try:
        result = capture(source, tmp_path / "out", quick(), detector=detector, lifter=lifter, progress=False, live_view=view)
    finally:
        view.stop()
    assert [len(s) for s in shown] == [1, 1, 1, 0, 1, 1, 1]
    assert (tmp_path / "out" / "capture.json").is_file() and len(result.people) == 1     # the blink bridged
    assert result.people[0].segment.frames.tolist() == list(range(7))
