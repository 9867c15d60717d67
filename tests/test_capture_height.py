"""Heights relative to a reference person (humotion.capture.height, capture's height_reference),
on held-out CMU mocap (test subjects 09 and 93) filmed by a virtual camera with detector-like
noise. Accuracy over many scenes is bench/height_from_reference.py's job; these check one walking
reference against a child and an adult, and the errors and fallbacks."""

import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion.canonical import to_canonical
from humotion.capture.height import (FloorContacts, contacts_of, estimate_heights, fit_floor,
                                     placed_on_floor)
from humotion.capture.keypoints import DetectorNoise, VirtualCamera, body_keypoints_3d, corrupt
from humotion.capture.lifting import load_lifter
from humotion.capture.pipeline import CaptureConfig, Segment, estimate_people_heights, initial_fit, lift_segment
from humotion.capture.refine import intrinsics
from humotion.cli import main
from humotion.io import load_motion
from humotion.motion import Motion

WALK = "cmu_sxaxmz/amc/09/09_12__walk.amc.gz"            # subject 09 walks across the room
DANCE = "cmu_sxaxmz/amc/93/93_06__dance,_lindyHop2.amc.gz"   # subject 93 dances about


@pytest.fixture(scope="module")
def clips(mocap):
    return {name: to_canonical(load_motion(mocap / path)).resample(30.0)[:180] for name, path in
            (("walk", WALK), ("dance", DANCE))}


@pytest.fixture(scope="module")
def lifter():
    return load_lifter()


def filmed(people: list[Motion], seed: int, eye=(1.0, 1.4, 7.5), size=(1280, 720)):
    """Segments (detector-like keypoints, ids 0, 1, ...) of people filmed by one camera of 60
    degrees (size: image pixels) at eye, looking at a point 0.7 m above the floor between them,
    and its intrinsics."""
    generator = torch.Generator().manual_seed(seed)
    camera = VirtualCamera.looking_at(torch.tensor(eye), torch.tensor([0.0, 0.7, 0.0]), 60.0, *size)
    segments = []
    for person, motion in enumerate(people):
        world_r, world_p = motion.world()
        pixels, depth = camera.project(body_keypoints_3d(world_r, world_p, motion.skeleton))
        noisy, confidence = corrupt(pixels, generator, DetectorNoise(), camera.size, depth)
        t = len(noisy)
        segments.append(Segment(person, np.arange(t), np.arange(t) / 30.0, noisy, confidence))
    return segments, intrinsics(camera)


@pytest.mark.parametrize("height", [1.15, 1.90])
def test_height_of_a_dancer_relative_to_a_walker(clips, lifter, height):
    """A child and a tall adult, each 2 m from a 1.75 m reference walking across the room: the
    estimate is within 15 cm where the 1.65 m default is 25-50 cm off."""
    walker = placed_on_floor(clips["walk"], 1.75, 0.5, (-1.0, 0.0))
    dancer = placed_on_floor(clips["dance"], height, 2.0, (1.0, 0.5))
    segments, camera = filmed([walker, dancer], seed=3)
    warnings = []
    config = CaptureConfig(heights={0: 1.75}, height_reference=0)
    estimated = estimate_people_heights(segments, camera, lifter, config, warnings)
    assert not warnings
    assert set(estimated) == {1}
    assert abs(estimated[1] - height) < 0.15, estimated


def test_people_with_given_heights_are_not_estimated(clips, lifter):
    segments, camera = filmed([placed_on_floor(clips["walk"], 1.75, 0.5, (-1.0, 0.0)),
                               placed_on_floor(clips["dance"], 1.3, 2.0, (1.0, 0.5))], seed=4)
    config = CaptureConfig(heights={0: 1.75, 1: 1.3}, height_reference=0)
    assert estimate_people_heights(segments, camera, lifter, config, []) == {}


def contacts(segments, camera, lifter, heights):
    out = {}
    for segment in segments:
        fit = initial_fit(segment, camera, lifter, heights[segment.person])
        out[segment.person] = contacts_of(fit.rotations, fit.root, fit.skeleton, torch.as_tensor(segment.confidence))
    return out


def test_nobody_moving_far_apart_keeps_the_default(clips, lifter):
    """Two people standing still 5 m apart in depth: the floor's tilt is left to the bodies'
    down direction, too unsure to place one relative to the other, so B keeps the default."""
    still = clips["walk"][:1]
    still = Motion(still.skeleton, still.rotations.expand(60, -1, -1), still.root_positions.expand(60, -1), 30.0)
    people = [placed_on_floor(still, 1.75, 0.3, (-0.5, 3.0)), placed_on_floor(still, 1.3, 1.0, (0.8, -2.0))]
    segments, camera = filmed(people, seed=5, eye=(0.0, 1.2, 9.0))
    found = contacts(segments, camera, lifter, {0: 1.75, 1: 1.65})
    heights, warnings = estimate_heights(found, {0: 1.75, 1: 1.65}, reference=0)
    assert heights == {}
    assert len(warnings) == 1 and "person 1 keeps 1.65 m" in warnings[0] and "not pinned down" in warnings[0]


def test_bad_references_are_errors(clips, lifter):
    segments, camera = filmed([placed_on_floor(clips["walk"], 1.75, 0.5, (-1.0, 0.0)),
                               placed_on_floor(clips["dance"], 1.3, 2.0, (1.0, 0.5))], seed=6)
    found = contacts(segments, camera, lifter, {0: 1.75, 1: 1.65})
    with pytest.raises(ValueError, match="person 7, was not found"):
        estimate_heights(found, {0: 1.75, 1: 1.65}, reference=7)
    feetless = dict(found)
    feetless[0] = FloorContacts(found[0].points, found[0].lift, torch.zeros_like(found[0].weight), found[0].down)
    with pytest.raises(ValueError, match="never seen with a foot on the floor"):
        estimate_heights(feetless, {0: 1.75, 1: 1.65}, reference=0)
    with pytest.raises(ValueError, match="needs a given height"):
        CaptureConfig(heights={1: 1.6}, height_reference=0)


def test_a_person_barely_on_the_floor_keeps_the_default(clips, lifter):
    segments, camera = filmed([placed_on_floor(clips["walk"], 1.75, 0.5, (-1.0, 0.0)),
                               placed_on_floor(clips["dance"], 1.3, 2.0, (1.0, 0.5))], seed=7)
    found = contacts(segments, camera, lifter, {0: 1.75, 1: 1.65})
    weight = found[1].weight.clone()
    weight[5:] = 0.0                                       # feet seen on 5 frames only
    found[1] = FloorContacts(found[1].points, found[1].lift, weight, found[1].down)
    heights, warnings = estimate_heights(found, {0: 1.75, 1: 1.65}, reference=0)
    assert heights == {} and "barely seen on the floor" in warnings[0]


def test_floor_normal_from_a_walker(clips, lifter):
    """The walker's contacts tilt the floor by at most a few degrees from the truth."""
    segments, camera = filmed([placed_on_floor(clips["walk"], 1.75, 0.5, (-1.0, 0.0))], seed=8)
    fit = fit_floor(contacts(segments, camera, lifter, {0: 1.75}), reference=0)
    truth = VirtualCamera.looking_at(torch.tensor((1.0, 1.4, 7.5)), torch.tensor([0.0, 0.7, 0.0]), 60.0, 1280, 720)
    down = truth.rotation @ torch.tensor([0.0, -1.0, 0.0])
    assert math.degrees(math.acos(min(1.0, float(fit.normal @ down)))) < 4.0
    assert fit.offsets[0] == pytest.approx(1.4, abs=0.15)   # the camera's height above the floor


def test_cli_needs_the_reference_height(tmp_path):
    result = CliRunner().invoke(main, ["capture", str(tmp_path / "missing.mp4"), "-o", str(tmp_path / "out"),
                                       "--height", "1=1.60", "--height-reference", "0"])
    assert result.exit_code != 0 and "person 0, needs a given height (--height 0=METRES" in result.output


class Scripted:
    """A PoseDetector that gives, per image, the next frame's detections of prepared segments."""

    def __init__(self, segments):
        self.segments, self.frame = segments, 0

    def detect(self, image):
        from humotion.capture.detection import Detection, keypoint_box

        found = []
        for s in self.segments:
            keypoints = s.keypoints[self.frame].numpy()           # a detector gives numpy
            confidence = s.confidence[self.frame].numpy()
            if confidence.max() > 0.3:
                found.append(Detection(keypoints, confidence, 0.9, keypoint_box(keypoints, confidence)))
        self.frame += 1
        return found


def test_capture_estimates_heights_relative_to_the_reference(tmp_path, clips, lifter, monkeypatch):
    """capture() with height_reference: the dancer's height estimated, used for their skeleton,
    and written to capture.json; each segment lifted once for both passes."""
    import json

    from humotion.capture import pipeline
    from humotion.capture.pipeline import capture

    lifted = []

    def counted(lifter, segment, camera):
        lifted.append(segment)
        return lift_segment(lifter, segment, camera)

    monkeypatch.setattr(pipeline, "lift_segment", counted)
    from humotion.capture.refine import CaptureRefineConfig
    from humotion.io.video import VideoWriter

    walker = placed_on_floor(clips["walk"][:90], 1.75, 0.5, (-1.0, 0.0))
    dancer = placed_on_floor(clips["dance"][:90], 1.2, 2.0, (1.0, 0.5))
    segments, _ = filmed([walker, dancer], seed=9, size=(320, 180))
    with VideoWriter(tmp_path / "two.mp4", fps=30.0) as writer:
        for _ in range(90):
            writer.write(np.full((180, 320, 3), 128, np.uint8))
    config = CaptureConfig(heights={0: 1.75}, height_reference=0, refine=CaptureRefineConfig(iterations=5, photo_iterations=5))
    result = capture(tmp_path / "two.mp4", tmp_path / "out", config, detector=Scripted(segments), lifter=lifter,
                     progress=False)
    assert set(result.estimated_heights) == {1} and not result.warnings
    assert len(lifted) == len(result.people) == 2
    assert abs(result.estimated_heights[1] - 1.2) < 0.15
    dancer_out = next(p for p in result.people if p.segment.person == 1)
    assert dancer_out.motion.skeleton.height() == pytest.approx(result.estimated_heights[1], rel=1e-3)
    saved = json.loads((tmp_path / "out" / "capture.json").read_text())
    assert saved["height_reference"] == 0 and saved["heights_m"]["1"] == pytest.approx(result.estimated_heights[1])
