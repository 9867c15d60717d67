"""One-Euro keypoint filter and multi-person tracking on synthetic people with known motion."""

import numpy as np
import pytest

from humotion.capture.detection import KEYPOINTS, Detection, keypoint_box
from humotion.capture.filters import OneEuroConfig, OneEuroFilter, smoothing_factor
from humotion.capture.people import PeopleTracker, body_proportions, proportion_difference

FPS = 30.0
K = len(KEYPOINTS)

# A standing person 1 unit tall, centred on x = 0 with the feet at y = 0 (y down: head negative).
_STANDING = {
    "nose": (0.0, -0.93), "left_eye": (0.03, -0.95), "right_eye": (-0.03, -0.95),
    "left_ear": (0.06, -0.93), "right_ear": (-0.06, -0.93),
    "left_shoulder": (0.13, -0.82), "right_shoulder": (-0.13, -0.82),
    "left_elbow": (0.16, -0.63), "right_elbow": (-0.16, -0.63),
    "left_wrist": (0.17, -0.48), "right_wrist": (-0.17, -0.48),
    "left_hip": (0.09, -0.53), "right_hip": (-0.09, -0.53),
    "left_knee": (0.09, -0.28), "right_knee": (-0.09, -0.28),
    "left_ankle": (0.09, -0.04), "right_ankle": (-0.09, -0.04),
    "left_heel": (0.09, 0.0), "right_heel": (-0.09, 0.0),
    "left_big_toe": (0.12, 0.0), "right_big_toe": (-0.12, 0.0),
}  # fmt: skip
STANDING = np.array([_STANDING[name] for name in KEYPOINTS])


def person(x: float, y: float, height: float = 200.0, legs: float = 1.0, noise: float = 0.0, rng=None) -> Detection:
    """A Detection of the standing figure with its feet at (x, y) pixels; legs scales the leg length."""
    shape = STANDING.copy()
    below_hips = shape[:, 1] > -0.53
    shape[below_hips, 1] = -0.53 + (shape[below_hips, 1] + 0.53) * legs
    keypoints = (shape * height + (x, y)).astype(np.float32)
    if noise:
        keypoints += rng.normal(0.0, noise, keypoints.shape).astype(np.float32)
    confidence = np.full(K, 0.9, np.float32)
    return Detection(keypoints, confidence, 0.9, keypoint_box(keypoints, confidence))


def run_filter(config: OneEuroConfig, signal: np.ndarray, confidence: np.ndarray | None = None, times=None):
    """Filter a (T, K, 2) signal; returns outputs (T, K, 2) and confidences (T, K)."""
    times = np.arange(len(signal)) / FPS if times is None else times
    confidence = np.ones(signal.shape[:2], np.float32) if confidence is None else confidence
    one_euro = OneEuroFilter(config)
    out = [one_euro(x, c, t) for x, c, t in zip(signal, confidence, times)]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])


# ---------------------------------------------------------------- One-Euro filter


def test_constant_signal_is_returned_exactly():
    keypoints = np.random.default_rng(0).uniform(0, 1000, (K, 2)).astype(np.float32)
    out, confidence = run_filter(OneEuroConfig(), np.repeat(keypoints[None], 60, axis=0))
    assert np.array_equal(out, np.broadcast_to(keypoints, out.shape))
    assert out.dtype == np.float32 and (confidence == 1).all()


def test_noise_on_a_still_point_shrinks_as_a_first_order_low_pass_predicts():
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 2.0, (900, K, 2))
    signal = 500.0 + noise
    # beta = 0: a plain low-pass, whose output variance is alpha / (2 - alpha) of white input noise.
    out, _ = run_filter(OneEuroConfig(beta=0.0, min_cutoff=1.0), signal)
    alpha = smoothing_factor(1 / FPS, 1.0)
    ratio = out[100:].var() / noise[100:].var()
    assert ratio == pytest.approx(alpha / (2 - alpha), rel=0.15)  # 0.095: about a tenth
    # The default beta lets the jitter raise the cutoff a little: still at least 3x less variance.
    out_default, _ = run_filter(OneEuroConfig(), signal)
    assert ratio < out_default[100:].var() / noise[100:].var() < 0.33
    assert abs(out_default[100:].mean() - 500.0) < 0.2


def test_larger_beta_lags_less_on_a_ramp():
    speed = 300.0  # pixels per second
    times = np.arange(120) / FPS
    ramp = np.repeat((speed * times)[:, None, None], K, axis=1).repeat(2, axis=2)
    lags = {}
    for beta in (0.0, 0.01, 0.05):
        out, _ = run_filter(OneEuroConfig(beta=beta), ramp)
        lags[beta] = float((ramp - out)[-1].mean())
    alpha = smoothing_factor(1 / FPS, 1.0)
    assert lags[0.0] == pytest.approx(speed / FPS * (1 - alpha) / alpha, rel=1e-3)  # steady-state lag: 48 px
    assert lags[0.0] > lags[0.01] > lags[0.05] > 0
    assert lags[0.05] < 0.15 * lags[0.0]


def test_zero_confidence_holds_the_keypoint_and_reports_confidence_zero():
    signal = np.repeat(np.arange(20.0)[:, None, None], K, axis=1).repeat(2, axis=2) * 10  # 10 px per frame
    confidence = np.ones((20, K), np.float32)
    confidence[8:12, 3] = 0.0
    signal[8:12, 3] = -1e4  # what a detector might put at an occluded point
    out, reported = run_filter(OneEuroConfig(), signal, confidence)
    assert (out[8:12, 3] == out[7, 3]).all() and (reported[8:12, 3] == 0).all()
    assert (reported[:, [0, 1, 2, 4]] == 1).all() and (np.diff(out[:12, 0, 0]) > 0).all()
    assert out[12, 3, 0] > out[7, 3, 0]  # back to following the signal


def test_a_held_keypoint_takes_the_whole_gap_as_its_time_step():
    config = OneEuroConfig(beta=0.0, min_cutoff=1.0)
    one_euro = OneEuroFilter(config)
    still, moved = np.zeros((K, 2)), np.zeros((K, 2))
    moved[0] = (100.0, 0.0)
    held = np.ones(K, np.float32)
    held[0] = 0.0
    one_euro(still, np.ones(K), 0.0)
    for t in np.arange(1, 30) / FPS:  # keypoint 0 unseen for one second
        one_euro(still, held, t)
    out, _ = one_euro(moved, np.ones(K), 1.0)
    assert out[0, 0] == pytest.approx(100.0 * smoothing_factor(1.0, 1.0), rel=1e-5)  # 86 px, not 17


def test_irregular_time_steps():
    config = OneEuroConfig(beta=0.0)
    times = np.cumsum(np.random.default_rng(2).uniform(0.01, 0.06, 50))
    step = np.zeros((50, K, 2))
    step[25:] = 10.0
    out, _ = run_filter(config, step, times=times)
    expected = 10.0 * (1 - np.cumprod(1 - smoothing_factor(np.diff(times[24:]), 1.0)))
    assert np.allclose(out[25:, 0, 0], expected, rtol=1e-5)


def test_never_seen_keypoint_passes_through_with_zero_confidence():
    one_euro = OneEuroFilter()
    keypoints = np.arange(2.0 * K).reshape(K, 2)
    confidence = np.ones(K)
    confidence[5] = 0.0
    out, reported = one_euro(keypoints, confidence, 0.0)
    assert np.array_equal(out, keypoints) and reported[5] == 0


def test_disabled_reset_and_bad_input():
    keypoints = np.random.default_rng(3).normal(size=(K, 2))
    off = OneEuroFilter(OneEuroConfig(enabled=False))
    for t in range(3):
        out, _ = off(keypoints + t, np.zeros(K), float(t))
        assert np.allclose(out, keypoints + t)
    one_euro = OneEuroFilter()
    one_euro(keypoints, np.ones(K), 1.0)
    with pytest.raises(ValueError, match="timestamps must increase"):
        one_euro(keypoints, np.ones(K), 1.0)
    with pytest.raises(ValueError, match=r"\(K, D\)"):
        one_euro(keypoints[:, 0], np.ones(K), 2.0)
    one_euro.reset()
    out, _ = one_euro(keypoints + 50, np.ones(K), 0.0)
    assert np.allclose(out, keypoints + 50)
    with pytest.raises(ValueError, match="positive"):
        OneEuroConfig(min_cutoff=0.0)


# ---------------------------------------------------------------- tracker


def ids_by_x(people) -> list[int]:
    """Ids of the tracked people from left to right (by their feet)."""
    return [p.id for p in sorted(people, key=lambda p: p.detection.keypoints[-1, 0])]


@pytest.mark.parametrize("hidden", [(), range(19, 23)], ids=["in-view", "B-hidden-behind-A"])
def test_two_people_crossing_paths_keep_their_ids(hidden):
    rng = np.random.default_rng(4)
    tracker = PeopleTracker()
    # A walks right, B walks left on the same line, 12 px per frame: they pass through each other
    # between frames 20 and 21, where B's nearest last position is A's (only velocity tells them apart).
    for frame in range(40):
        a = person(100 + 12 * frame, 400, noise=2.0, rng=rng)
        b = person(586 - 12 * frame, 400, noise=2.0, rng=rng)
        detections = [a] if frame in hidden else [b, a] if frame % 2 else [a, b]  # order means nothing
        people = tracker.update(detections, frame / FPS)
        expected = {0: id(a)} if frame in hidden else {0: id(a), 1: id(b)}
        assert {p.id: id(p.detection) for p in people} == expected, f"frame {frame}"


def test_person_leaving_for_a_few_frames_gets_their_id_back():
    tracker = PeopleTracker(max_age=10)
    for frame in range(10):
        assert [p.id for p in tracker.update([person(300, 400), person(700, 400)], frame / FPS)] == [0, 1]
    for frame in range(10, 16):  # person 0 hidden (occluded, or out of the picture) for 6 frames
        assert [p.id for p in tracker.update([person(700, 400)], frame / FPS)] == [1]
    people = tracker.update([person(310, 402), person(700, 400)], 16 / FPS)
    assert ids_by_x(people) == [0, 1]
    people = tracker.update([person(320, 400), person(700, 400), person(1100, 400)], 17 / FPS)
    assert ids_by_x(people) == [0, 1, 2]  # a newcomer gets a new id


def test_ids_are_never_reused():
    tracker = PeopleTracker(max_age=3)
    tracker.update([person(300, 400)], 0.0)
    for frame in range(1, 6):  # gone for longer than max_age: the track is dropped
        assert tracker.update([], frame / FPS) == []
    assert [p.id for p in tracker.update([person(300, 400)], 6 / FPS)] == [1]
    tracker.reset()
    assert [p.id for p in tracker.update([person(300, 400)], 0.0)] == [2]


def test_someone_else_appearing_where_a_person_left_only_takes_their_id_when_near():
    tracker = PeopleTracker(max_age=10, max_distance=0.5)
    tracker.update([person(300, 400)], 0.0)
    tracker.update([], 1 / FPS)
    assert [p.id for p in tracker.update([person(600, 400)], 2 / FPS)] == [1]  # 1.5 heights away: new


def test_reidentification_by_body_proportions():
    long_legs, short_legs = person(300, 400, legs=1.3), person(300, 400, legs=0.8)
    assert proportion_difference(body_proportions(long_legs.keypoints, long_legs.confidence),
                                 body_proportions(short_legs.keypoints, short_legs.confidence)) > 0.1
    tracker = PeopleTracker(max_age=30, proportion_tolerance=0.05)
    tracker.update([long_legs, person(900, 400, legs=0.8)], 0.0)
    tracker.update([person(900, 400, legs=0.8)], 1 / FPS)  # person 0 leaves on the left ...
    # ... and comes back on the far right, smaller (farther away) but with the same build.
    people = tracker.update([person(900, 400, legs=0.8), person(1500, 350, height=150, legs=1.3)], 2 / FPS)
    assert ids_by_x(people) == [1, 0]
    without = PeopleTracker(max_age=30)
    without.update([long_legs], 0.0)
    without.update([], 1 / FPS)
    assert [p.id for p in without.update([person(1500, 350, height=150, legs=1.3)], 2 / FPS)] == [1]


def test_tracked_keypoints_are_filtered_per_person():
    rng = np.random.default_rng(5)
    raw = PeopleTracker(filter_config=OneEuroConfig(enabled=False))
    smooth = PeopleTracker()
    errors = {"raw": [], "smooth": []}
    truth = person(300, 400).keypoints
    for frame in range(60):
        detection = person(300, 400, noise=3.0, rng=rng)
        for name, tracker in (("raw", raw), ("smooth", smooth)):
            (tracked,) = tracker.update([detection], frame / FPS)
            assert tracked.keypoints.shape == (K, 2) and tracked.confidence.shape == (K,)
            errors[name].append(np.abs(tracked.keypoints - truth).mean())
    assert np.array_equal(tracked.detection.keypoints, detection.keypoints)
    assert np.mean(errors["smooth"][20:]) < 0.5 * np.mean(errors["raw"][20:])


def test_tracker_rejects_time_going_backwards():
    tracker = PeopleTracker()
    tracker.update([person(300, 400)], 1.0)
    with pytest.raises(ValueError, match="timestamps must increase"):
        tracker.update([person(300, 400)], 0.5)


# ---------------------------------------------------------------- identity: colours, occlusion, return

def coloured(detection: Detection, colour: int) -> Detection:
    """The detection with a torso-colour histogram mostly in bin `colour` (a stand-in for a shirt)."""
    histogram = np.full(128, 0.2 / 127, np.float32)
    histogram[colour] = 0.8
    return Detection(detection.keypoints, detection.confidence, detection.score, detection.box, histogram)


def test_torso_histogram_tells_shirts_apart():
    from humotion.capture.people import colour_distance, torso_histogram

    image = np.zeros((400, 400, 3), np.uint8)
    image[:, :200] = (200, 30, 30)   # red shirt on the left
    image[:, 200:] = (30, 30, 200)   # blue on the right
    left, right = person(100, 380, height=300), person(300, 380, height=300)
    red, blue = (torso_histogram(image, p.keypoints, p.confidence) for p in (left, right))
    assert red.shape == (128,) and abs(red.sum() - 1) < 1e-5
    assert colour_distance(red, red) < 0.01 and colour_distance(red, blue) > 0.9
    unsure = left.confidence.copy()
    unsure[KEYPOINTS.index("left_hip")] = 0.1
    assert torso_histogram(image, left.keypoints, unsure) is None


def test_crossing_with_both_hidden_keeps_ids_by_colour():
    # A and B walk towards each other at 10 px per frame and are not detected for 6 frames while
    # they pass (behind a pillar); they come out on the other side, each keeping their id.
    tracker = PeopleTracker()
    seen = {}
    for frame in range(40):
        a = coloured(person(200 + 10 * frame, 400), 3)
        b = coloured(person(590 - 10 * frame, 400), 90)
        detections = [] if 17 <= frame < 23 else [b, a]
        for p in tracker.update(detections, frame / FPS):
            seen.setdefault(p.id, set()).add(int(np.argmax(p.detection.appearance)))
    assert seen == {0: {90}, 1: {3}}


def test_side_by_side_walkers_are_not_swapped_when_one_is_missed():
    # Two people 80 px apart walk together; the left one is missed on some frames. A swap would put
    # the right one's detection on the left one's track.
    tracker = PeopleTracker()
    for frame in range(30):
        left = coloured(person(300 + 5 * frame, 400), 10)
        right = coloured(person(380 + 5 * frame, 400), 70)
        detections = [right] if frame % 4 == 3 else [left, right]
        for p in tracker.update(detections, frame / FPS):
            assert p.id == (0 if np.argmax(p.detection.appearance) == 10 else 1), f"frame {frame}"


def test_a_person_whose_torso_colours_flicker_keeps_their_id():
    # A small person's torso is a few dozen pixels: one frame's histogram can sit 0.6-0.8 away from
    # their running colours (bench/capture_people.py measured 1-9% of a person's frames above 0.6).
    # Found where they were a frame earlier, they are still themselves.
    from humotion.capture.people import colour_distance

    tracker = PeopleTracker()
    for frame in range(10):
        (p,) = tracker.update([coloured(person(200 + 5 * frame, 400), 3)], frame / FPS)
    flicker = coloured(person(250, 400), 3)
    histogram = 0.15 * flicker.appearance + 0.85 * coloured(flicker, 40).appearance
    flicker = Detection(flicker.keypoints, flicker.confidence, flicker.score, flicker.box, histogram)
    assert 0.6 < colour_distance(coloured(flicker, 3).appearance, histogram) < 0.8
    assert [p.id for p in tracker.update([flicker], 10 / FPS)] == [0]


def test_a_person_returning_after_seconds_elsewhere_gets_their_id_back():
    tracker = PeopleTracker()  # lost tracks are kept for 3 s
    for frame in range(15):
        tracker.update([coloured(person(200, 400), 3), coloured(person(900, 400), 60)], frame / FPS)
    for frame in range(15, 75):  # person 0 away for two seconds ...
        assert [p.id for p in tracker.update([coloured(person(900, 400), 60)], frame / FPS)] == [1]
    # ... and back at the other side of the picture, next to a newcomer in other colours
    people = tracker.update([coloured(person(900, 400), 60), coloured(person(1400, 400), 3),
                             coloured(person(500, 400), 120)], 75 / FPS)
    assert {int(np.argmax(p.detection.appearance)): p.id for p in people} == {60: 1, 3: 0, 120: 2}


def test_a_person_gone_longer_than_kept_gets_a_new_id():
    tracker = PeopleTracker(max_lost_seconds=1.0)
    tracker.update([coloured(person(200, 400), 3)], 0.0)
    assert tracker.update([], 0.5) == []
    assert [p.id for p in tracker.update([coloured(person(200, 400), 3)], 1.6)] == [1]


def test_predicted_boxes_move_with_the_person():
    tracker = PeopleTracker()
    for frame in range(5):
        tracker.update([person(200 + 10 * frame, 400)], frame / FPS)
    ((pid, box),) = tracker.predicted_boxes(5 / FPS)
    last = person(240, 400).box
    assert pid == 0 and abs(box[0] - (last[0] + 10)) < 2 and abs(box[3] - last[3]) < 1


class _StillPersonDetector:
    """A top-down detector (detect_regions, detect_near, refine) that always sees one standing
    person, counting its scans."""

    tile = 256

    def __init__(self):
        self.scans = 0
        self.regions: list[int] = []   # regions searched, per scan

    def detect(self, image):
        return [person(300.0, 400.0)]

    def detect_regions(self, image, regions):
        self.scans += 1
        self.regions.append(len(regions))
        return [person(300.0, 400.0)]

    def refine(self, image, detections):
        return list(detections)

    def detect_near(self, image, boxes):
        return [person(300.0, 400.0) for _ in boxes]


@pytest.mark.parametrize("fps, interval, scan_every", [(30.0, None, 3), (10.0, None, 1), (30.0, 0.0, 1)])
def test_while_someone_is_followed_the_scan_runs_every_tenth_of_a_second(fps, interval, scan_every):
    from humotion.capture.follow import PeopleFinder

    detector = _StillPersonDetector()
    options = {} if interval is None else {"scan_interval": interval}           # None: the default, 0.1 s
    finder = PeopleFinder(detector, PeopleTracker(), appearance=False, **options)
    image = np.zeros((480, 640, 3), np.uint8)
    for frame in range(12):
        assert [p.id for p in finder(image, frame / fps)] == [0]
    assert detector.scans == 1 + len(range(scan_every, 12, scan_every))   # the first frame: nobody followed yet


def test_the_first_frame_is_searched_everywhere_then_a_region_per_scan():
    # Everyone in view at the start is found at the start, as in a photo; then the scan goes on a
    # region at a time. Without the full first search, a 2 x 2 mosaic of the hikers clip (20-24
    # small people) found 7 of 24 people on its first frame (bench/capture_people.py --mosaic 2).
    from humotion.capture.follow import PeopleFinder
    from humotion.capture.movenet import scan_regions

    detector = _StillPersonDetector()
    finder = PeopleFinder(detector, PeopleTracker(), appearance=False, scan_interval=0.0)
    image = np.zeros((480, 640, 3), np.uint8)
    for frame in range(3):
        finder(image, frame / 30.0)
    finder(np.zeros((240, 320, 3), np.uint8), 3 / 30.0)       # a new size: searched everywhere again
    assert detector.regions == [len(scan_regions(640, 480)), 1, 1, len(scan_regions(320, 240))]
