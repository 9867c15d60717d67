"""The camera's horizon and height from upright people in the image alone
(humotion.capture.metrology): known answers from synthetic scenes, and a real fixed camera."""

import numpy as np
import pytest
import torch

from humotion.capture.camera import CameraPose, up_from_pitch
from humotion.capture.detection import KEYPOINTS
from humotion.capture.metrology import LANDMARK_LEVELS, camera_from_people, standing_levels, upright_midpoints
from humotion.capture.pipeline import default_camera
from tests.test_capture_camera import standing_people

CAMERA = default_camera(768, 432)


def filmed(places, pose: CameraPose, noise_px: float = 1.0, seed: int = 0, height_m: float = 1.7):
    """(keypoints (N, 21, 2), confidence (N, 21)): people standing at places (x, z), seen through
    the camera at pose, with Gaussian pixel noise; their ankles, hips and shoulders where a
    detector marks them (LANDMARK_LEVELS: the template body's joint centres sit elsewhere)."""
    rng = np.random.default_rng(seed)
    seen = pose.camera_in_world(CAMERA)
    points = torch.stack([k for _, k in standing_people(places, height_m)])
    for pair, level in zip(("ankle", "hip", "shoulder"), LANDMARK_LEVELS):
        points[:, [KEYPOINTS.index(f"{side}_{pair}") for side in ("left", "right")], 1] = level * height_m
    pixels = seen.project(points)[0].numpy()
    return pixels + rng.normal(0, noise_px, pixels.shape), np.full(pixels.shape[:2], 0.8)


def places_ahead(count: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    return list(zip(rng.uniform(-2.5, 2.5, count), rng.uniform(-9.0, -3.5, count)))


@pytest.mark.parametrize("pitch, roll, height", [(29.0, 1.0, 2.3), (5.0, -2.0, 1.5), (45.0, 0.0, 4.0)])
def test_people_at_many_places_give_the_horizon_and_the_height(pitch, roll, height):
    truth = CameraPose(up_from_pitch(pitch, roll), height, "given")
    keypoints, confidence = filmed(places_ahead(120), truth)
    found = camera_from_people([keypoints], [confidence], [1.7], CAMERA)
    assert found is not None and found.source == "people in the image"
    assert found.pitch_deg == pytest.approx(pitch, abs=1.0) and found.roll_deg == pytest.approx(roll, abs=1.0)
    assert found.height == pytest.approx(height, rel=0.05)


def test_the_height_scales_with_the_people_and_one_place_is_not_enough():
    truth = CameraPose(up_from_pitch(20.0), 2.0, "given")
    keypoints, confidence = filmed(places_ahead(120), truth, height_m=1.7)
    taller = camera_from_people([keypoints], [confidence], [1.87], CAMERA)    # people assumed 10% taller
    assert taller.height == pytest.approx(2.2, rel=0.05)
    still, seen = filmed([(0.5, -5.0)] * 60, truth, noise_px=2.0)
    assert camera_from_people([still], [seen], [1.7], CAMERA) is None         # one distance: height unsure
    assert camera_from_people([keypoints[:10]], [confidence[:10]], [1.7], CAMERA) is None   # too few frames


def test_only_upright_frames_are_used():
    truth = CameraPose(up_from_pitch(20.0), 2.0, "given")
    keypoints, confidence = filmed(places_ahead(5), truth)
    assert len(upright_midpoints(keypoints, confidence)) == 5
    bent = keypoints.copy()
    bent[:, 13:15, 0] += 40.0                                                 # knees far off the legs' line
    assert len(upright_midpoints(bent, confidence)) == 0
    unsure = confidence.copy()
    unsure[:, 5] = 0.1                                                        # a shoulder not seen
    assert len(upright_midpoints(keypoints, unsure)) == 0
    assert standing_levels(1.7) == pytest.approx(standing_levels(1.0) * 1.7)
    assert 0.0 < standing_levels(1.7)[0] < 0.15 and 1.3 < standing_levels(1.7)[2] < 1.5   # ankles, shoulders


def test_the_floor_drawing_puts_the_grid_below_the_horizon():
    from humotion.capture.overlay import draw_floor

    camera = default_camera(320, 240)
    image = np.zeros((240, 320, 3), np.uint8)
    drawn = draw_floor(image, camera, CameraPose(up_from_pitch(0.0), 1.5, "given"))
    white = np.flatnonzero((drawn == 255).all(-1).any(1))
    assert white.size and abs(np.median(white) - 120) <= 2                    # a level camera: the horizon mid-image
    grid = (drawn[..., 0] > 80) & (drawn[..., 1] > 60) & (drawn[..., 2] < 40)     # yellow, antialiased
    assert grid[130:].sum() > 500 and grid[:115].sum() == 0                   # floor lines below it only
    pitched = draw_floor(image, camera, CameraPose(up_from_pitch(10.0), 1.5, "given"))
    white = np.flatnonzero((pitched == 255).all(-1).any(1))
    assert np.median(white) < 120 - 0.9 * camera.fy.item() * np.tan(np.radians(10.0))   # pitched down: it rises


def test_a_fixed_high_camera_is_found_from_the_person_standing_in_front_of_it():
    """10 s of the Intel clip (../shared/data/video, CC BY 4.0): a person at a table seen from
    behind by a high fixed camera. The lifter sees them crouching (the camera fell back to level);
    their image gives the camera pitched down about 37 degrees, 2.4 m high. The room's lines (the
    floorboards' and a window's vanishing points, with the 60 degree field of view assumed) put
    its pitch at 34-38 degrees (29 with the template body's joint centres as the landmarks)."""
    from pathlib import Path

    from humotion.capture.follow import PeopleFinder, make_detector
    from humotion.capture.people import PeopleTracker
    from humotion.io.video import open_frames

    video = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "intel_one-by-one-person-detection_first40s.mp4"
    if not video.is_file():
        pytest.skip("shared videos missing")
    finder = PeopleFinder(make_detector("movenet"), PeopleTracker())
    keypoints, confidence = [], []
    with open_frames(video) as frames:
        for index, time, image in frames:
            if index >= 340:
                break
            if index >= 240:
                for person in finder(image, time):
                    keypoints.append(person.keypoints)
                    confidence.append(person.confidence)
    camera = default_camera(768, 432)
    found = camera_from_people([np.stack(keypoints)], [np.stack(confidence)], [1.65], camera)
    assert found is not None and found.source == "people in the image"
    assert 32.0 < found.pitch_deg < 40.0 and abs(found.roll_deg) < 3.0 and 2.0 < found.height < 2.9, found


def test_a_short_clip_of_a_few_people_still_gives_the_camera():
    """The whole aisle clip (../shared/data/video, CC BY 4.0): 4.5 s, a high fixed camera over a
    shop aisle, one man standing upright and others reaching or half hidden: about 25 upright
    frames at one or two places, so the fit's pitch is unsure by about 3 degrees. The floor of
    the lifted people's feet put the camera 6 degrees down and rolled 13 (people leaning 30-40
    degrees); the aisle's floor lines show it looking down steeply, and the people's image
    gives about 37 degrees. A limit of 1 degree on the fit's uncertainty threw it away."""
    from pathlib import Path

    from humotion.capture.follow import PeopleFinder, make_detector
    from humotion.capture.people import PeopleTracker
    from humotion.io.video import open_frames

    video = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "intel_store-aisle-detection.gif"
    if not video.is_file():
        pytest.skip("shared videos missing")
    finder = PeopleFinder(make_detector("movenet"), PeopleTracker())
    people: dict[int, list] = {}
    with open_frames(video) as frames:
        for _, time, image in frames:
            for person in finder(image, time):
                people.setdefault(person.id, []).append((person.keypoints, person.confidence))
    tracks = [(np.stack([k for k, _ in seen]), np.stack([c for _, c in seen])) for seen in people.values()]
    found = camera_from_people([k for k, _ in tracks], [c for _, c in tracks], [1.7] * len(tracks), default_camera(480, 270))
    assert found is not None and found.source == "people in the image"
    assert 25.0 < found.pitch_deg < 42.0 and abs(found.roll_deg) < 8.0 and 2.0 < found.height < 3.6, found
