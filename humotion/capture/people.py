"""Following several people through a video: a stable integer id per person, and smoothed keypoints.

Each frame, the people detected are matched to the tracks of the people known so far with the
Hungarian algorithm (scipy's linear_sum_assignment) on a keypoint distance: the confidence-weighted
mean distance between a track's keypoints and a detection's, in units of the track's size (the
longer side of its keypoint box). A track's keypoints are taken where they were last seen and
where its constant velocity would have carried them since; the nearer of the two counts. The
velocity keeps two people apart when they cross paths (their boxes then overlap both ways, which
is why box IoU is not used); the last-seen position lets a person who stood still, or left the
picture, be found where they left.

Appearance: when detections carry a colour histogram of the torso (`torso_histogram`, filled
in by humotion.capture.follow.PeopleFinder), a pairing also costs the Bhattacharyya distance
between the detection's histogram and the track's running mean, and pairings whose colours differ
by more than `max_colour_distance` are refused: two people side by side, or crossing, keep their
ids when one of them is briefly not detected.

Tracks seen in the previous frame are matched first, then missing tracks (kept for
`max_lost_seconds`, or `max_age` frames when given) to the detections left over: near where they
were last seen or where their velocity (carried on for at most half a second) takes them; and,
failing that, anywhere in the picture when their torso colours match closely (`reid_colour_distance`)
and their size is alike, so that someone who leaves and comes back within a few seconds gets their
id again. Optionally a missing person is also recognised by their body proportions. A detection
matched to no track starts a new one with a new id; ids are never reused. Each track smooths its
keypoints with its own One-Euro filter.

Why by hand rather than a tracking library (norfair, motpy): their matching works on boxes or on
points with a distance of the library's design, their Kalman state replaces the velocity and the
One-Euro filter that humotion's 3D steps rely on, and none matches on keypoints and torso colour
together; what is left (a cost matrix and scipy's linear_sum_assignment) is short.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from humotion.capture.detection import KEYPOINT_BONES, KEYPOINTS, Detection
from humotion.capture.filters import OneEuroConfig, OneEuroFilter

_BODY_KEYPOINTS = range(KEYPOINTS.index("left_shoulder"), KEYPOINTS.index("right_ankle") + 1)
_PROPORTION_BONES = np.array([b for b in KEYPOINT_BONES if b[0] in _BODY_KEYPOINTS and b[1] in _BODY_KEYPOINTS])
"""Torso and limb bones (shoulders to ankles), whose length ratios describe a body."""

_NO_MATCH = 1e9  # cost of a forbidden pairing (outside the gates)


@dataclass
class TrackedPerson:
    """One person in one frame, as the tracker reports them.

    id: the person's integer id, the same in every frame, never given to anyone else.
    keypoints: (21, 2) float32 pixels in `KEYPOINTS` order, smoothed by the track's One-Euro filter
        (the detection's own when filtering is off).
    confidence: (21,) float32 in [0, 1]; 0 for a keypoint held at its last smoothed position.
    detection: the detection this frame's keypoints come from.
    """

    id: int
    keypoints: np.ndarray
    confidence: np.ndarray
    detection: Detection


_TORSO = [KEYPOINTS.index(name) for name in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")]
_HIST_BINS = (8, 4, 4)  # hue, saturation, value


def torso_histogram(image: np.ndarray, keypoints: np.ndarray, confidence: np.ndarray,
                    min_confidence: float = 0.3) -> np.ndarray | None:
    """A person's torso colours: a normalised HSV histogram (8 hue x 4 saturation x 4 value bins,
    float32 (128,), sum 1) of the box between their shoulders and hips, shrunk by a fifth on each
    side to stay on the clothes; None when a shoulder or hip is below min_confidence or the box is
    under 4 px. image: (H, W, 3) uint8 RGB; keypoints (21, 2) pixels; confidence (21,)."""
    if (confidence[_TORSO] < min_confidence).any():
        return None
    x0, y0 = keypoints[_TORSO].min(axis=0)
    x1, y1 = keypoints[_TORSO].max(axis=0)
    dx, dy = 0.2 * (x1 - x0), 0.2 * (y1 - y0)
    height, width = image.shape[:2]
    x0, x1 = int(max(x0 + dx, 0)), int(min(x1 - dx, width))
    y0, y1 = int(max(y0 + dy, 0)), int(min(y1 - dy, height))
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    hsv = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_RGB2HSV)
    hist = cv2.calcHist([hsv], [0, 1, 2], None, list(_HIST_BINS), [0, 180, 0, 256, 0, 256]).ravel()
    return (hist / max(hist.sum(), 1.0)).astype(np.float32)


def colour_distance(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Bhattacharyya distance in [0, 1] between two `torso_histogram`s (each a normalised (128,)
    float32 histogram; 0: same colours); NaN if either is None."""
    if a is None or b is None:
        return float("nan")
    return float(np.sqrt(max(0.0, 1.0 - float(np.sqrt(a * b).sum()))))


def keypoint_distances(
    points: np.ndarray, confidence: np.ndarray, other: np.ndarray, other_confidence: np.ndarray
) -> np.ndarray:
    """Mean keypoint distance between every pair of people, weighted by both confidences.

    points: (P, K, 2), confidence (P, K); other: (D, K, 2), other_confidence (D, K). Returns (P, D)
    in the units of the points. A pair with no keypoint confident in both uses plain means.
    """
    distance = np.linalg.norm(points[:, None] - other[None], axis=-1)  # (P, D, K)
    weight = confidence[:, None] * other_confidence[None] + 1e-6
    return (distance * weight).sum(-1) / weight.sum(-1)


def body_proportions(keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.5) -> np.ndarray:
    """Log lengths of the torso and limb bones, (bones,); NaN for a bone with an end below min_confidence.

    keypoints (21, 2), confidence (21,). Differences of these between two people, less their mean,
    compare body shapes independently of distance to the camera (see `proportion_difference`).
    """
    start, end = _PROPORTION_BONES.T
    length = np.linalg.norm(keypoints[end] - keypoints[start], axis=-1)
    sure = (confidence[start] >= min_confidence) & (confidence[end] >= min_confidence) & (length > 0)
    return np.where(sure, np.log(np.where(sure, length, 1.0)), np.nan)


def proportion_difference(a: np.ndarray, b: np.ndarray, min_bones: int = 4) -> float:
    """Mean absolute log-ratio of bone lengths between two `body_proportions` (bones,), after
    removing scale.

    About the relative difference of bone proportions: 0.1 is bones 10 % off. Infinity when fewer
    than min_bones bones are known in both.
    """
    both = ~(np.isnan(a) | np.isnan(b))
    if both.sum() < min_bones:
        return np.inf
    ratio = a[both] - b[both]
    return float(np.abs(ratio - ratio.mean()).mean())


class _Track:
    """One person's state: last observation, velocity, proportions, filter."""

    def __init__(self, track_id: int, filter_config: OneEuroConfig):
        self.id = track_id
        self.filter = OneEuroFilter(filter_config)
        self.velocity = np.zeros(2)  # pixels per second, of the whole body
        self.missed = 0  # frames since last seen
        self._proportion_sum = np.zeros(len(_PROPORTION_BONES))
        self._proportion_count = np.zeros(len(_PROPORTION_BONES))
        self.detection: Detection | None = None  # the last one seen
        self.seen_at = 0.0  # seconds
        self.colours: np.ndarray | None = None  # running mean torso_histogram

    @property
    def size(self) -> float:
        """Pixels: the longer side of the last seen keypoint box."""
        x0, y0, x1, y1 = self.detection.box
        return max(x1 - x0, y1 - y0, 1.0)

    @property
    def proportions(self) -> np.ndarray:
        """(bones,) mean `body_proportions` over the frames the person was seen in; NaN for unseen bones."""
        with np.errstate(invalid="ignore"):
            return self._proportion_sum / self._proportion_count

    def hypotheses(self, timestamp: float) -> np.ndarray:
        """(2, 21, 2) pixels: the keypoints where last seen, and moved on at the track's velocity
        (for at most half a second: a constant velocity is not kept up for longer)."""
        last = self.detection.keypoints.astype(np.float64)
        return np.stack([last, last + self.velocity * min(timestamp - self.seen_at, 0.5)])

    def predicted_box(self, timestamp: float) -> tuple[float, float, float, float]:
        """The last keypoint box moved on at the track's velocity (at most half a second)."""
        dx, dy = self.velocity * min(timestamp - self.seen_at, 0.5)
        x0, y0, x1, y1 = self.detection.box
        return x0 + dx, y0 + dy, x1 + dx, y1 + dy

    def observe(self, detection: Detection, timestamp: float) -> TrackedPerson:
        """Take this frame's detection: update velocity (after the first), proportions and filter."""
        previous = self.detection
        if previous is not None:
            weight = previous.confidence * detection.confidence + 1e-6
            shift = ((detection.keypoints - previous.keypoints) * weight[:, None]).sum(0) / weight.sum()
            velocity = shift / (timestamp - self.seen_at)
            self.velocity = velocity if self.missed else 0.5 * (self.velocity + velocity)  # steadier
        self.detection, self.seen_at, self.missed = detection, timestamp, 0
        if detection.appearance is not None:
            self.colours = (detection.appearance if self.colours is None
                            else 0.8 * self.colours + 0.2 * detection.appearance)
        logs = body_proportions(detection.keypoints, detection.confidence)
        known = ~np.isnan(logs)
        self._proportion_sum[known] += logs[known]
        self._proportion_count[known] += 1
        keypoints, confidence = self.filter(detection.keypoints, detection.confidence, timestamp)
        return TrackedPerson(self.id, keypoints, confidence, detection)


class PeopleTracker:
    """Gives each person a stable id across frames and smooths their keypoints; see the module doc.

    max_age: None, or frames a person may go unseen and still get their id back (instead of
        max_lost_seconds).
    max_lost_seconds: how long a person may go unseen and still get their id back.
    max_distance: the farthest a detection may be from a track's keypoints to be that person, in
        units of the person's size (the longer side of their keypoint box).
    colour_weight: how much a torso-colour difference (`colour_distance`, 0 to 1) adds to a
        pairing's cost, in person sizes. max_colour_distance: pairings whose torso colours differ
        more are refused. A person's own histogram is noisy on a torso a few dozen pixels across,
        so the gate is loose (the capture model card has the measurement behind it). reid_colour_distance: a missing person is recognised away from where
        they left when their torso colours differ by at most this (and their size is within a
        factor 1.5); None: never.
    filter_config: the One-Euro filter of every track (OneEuroConfig(enabled=False) for raw keypoints).
    proportion_tolerance: None, or the largest `proportion_difference` at which a missing person is
        recognised away from where they left (e.g. 0.08). Proportions seen in 2D change with the
        view, so this can confuse people of similar build; off by default.
    """

    def __init__(
        self,
        max_age: int | None = None,
        max_distance: float = 0.5,
        filter_config: OneEuroConfig | None = None,
        proportion_tolerance: float | None = None,
        max_lost_seconds: float = 3.0,
        colour_weight: float = 0.5,
        max_colour_distance: float = 0.8,
        reid_colour_distance: float | None = 0.3,
    ):
        if (max_age is not None and max_age < 0) or not max_distance > 0 or max_lost_seconds < 0:
            raise ValueError(f"need max_age >= 0, max_distance > 0 and max_lost_seconds >= 0, got {max_age}, "
                             f"{max_distance} and {max_lost_seconds}")
        self.max_age, self.max_distance, self.max_lost_seconds = max_age, max_distance, max_lost_seconds
        self.colour_weight, self.max_colour_distance = colour_weight, max_colour_distance
        self.reid_colour_distance = reid_colour_distance
        self.filter_config = filter_config if filter_config is not None else OneEuroConfig()
        self.proportion_tolerance = proportion_tolerance
        self._tracks: list[_Track] = []
        self._next_id = 0
        self._last_timestamp: float | None = None

    def update(self, detections: list[Detection], timestamp: float) -> list[TrackedPerson]:
        """The people of one frame, by id: detections of the frame, timestamp in seconds (increasing).

        Returns one TrackedPerson per detection, sorted by id. People not detected in this frame
        are not reported; their tracks wait up to max_age frames for them.
        """
        if self._last_timestamp is not None and not timestamp > self._last_timestamp:
            raise ValueError(f"timestamps must increase: got {timestamp} s after {self._last_timestamp} s")
        self._last_timestamp = timestamp
        self._tracks = [t for t in self._tracks if self._kept(t, timestamp)]  # gone too long: forgotten
        seen = [t for t in self._tracks if t.missed == 0]
        missing = [t for t in self._tracks if t.missed > 0]
        people, left = [], list(range(len(detections)))
        for group, reidentify in ((seen, False), (missing, True)):
            pairs = self._match(group, [detections[i] for i in left], timestamp, reidentify)
            people += [group[t].observe(detections[left[d]], timestamp) for t, d in pairs]
            taken = {left[d] for _, d in pairs}
            left = [i for i in left if i not in taken]
        matched = {person.id for person in people}
        for track in self._tracks:
            if track.id not in matched:
                track.missed += 1
        self._tracks = [t for t in self._tracks if self._kept(t, timestamp)]
        for i in left:
            track = _Track(self._next_id, self.filter_config)
            self._next_id += 1
            self._tracks.append(track)
            people.append(track.observe(detections[i], timestamp))
        return sorted(people, key=lambda person: person.id)

    def _kept(self, track: _Track, timestamp: float) -> bool:
        if self.max_age is not None:
            return track.missed <= self.max_age
        return timestamp - track.seen_at <= self.max_lost_seconds

    def predicted_boxes(self, timestamp: float, max_missed: int = 2) -> list[tuple[int, tuple[float, float, float, float]]]:
        """[(id, (x0, y0, x1, y1) pixels)]: where the people seen in the last max_missed + 1 frames
        should be at timestamp (their keypoint box moved on at their velocity)."""
        return [(t.id, t.predicted_box(timestamp)) for t in self._tracks if t.missed <= max_missed]

    def last_seen(self) -> dict[int, Detection]:
        """{id: detection} of the people found in the last frame."""
        return {t.id: t.detection for t in self._tracks if t.missed == 0}

    def reset(self) -> None:
        """Forget everyone (for a new video); ids keep counting up, so none is reused."""
        self._tracks, self._last_timestamp = [], None

    def _match(
        self, tracks: list[_Track], detections: list[Detection], timestamp: float, reidentify: bool
    ) -> list[tuple[int, int]]:
        """(track index, detection index) pairs with the least total cost inside the gates."""
        if not tracks or not detections:
            return []
        from scipy.optimize import linear_sum_assignment   # here: scipy.optimize costs every `humotion` start 0.4 s

        cost = self._costs(tracks, detections, timestamp, reidentify)
        rows, cols = linear_sum_assignment(cost)
        return [(r, c) for r, c in zip(rows, cols) if cost[r, c] < _NO_MATCH]

    def _costs(
        self, tracks: list[_Track], detections: list[Detection], timestamp: float, reidentify: bool
    ) -> np.ndarray:
        """(P, D) keypoint distances, tracks by detections, in person sizes; _NO_MATCH outside the gates."""
        points = np.stack([d.keypoints for d in detections]).astype(np.float64)
        confidence = np.stack([d.confidence for d in detections])
        track_confidence = np.stack([t.detection.confidence for t in tracks])
        distance = np.minimum.reduce([
            keypoint_distances(hypothesis, track_confidence, points, confidence)
            for hypothesis in np.stack([t.hypotheses(timestamp) for t in tracks], axis=1)
        ]) / np.array([[t.size] for t in tracks])  # fmt: skip
        colours = np.array([[colour_distance(t.colours, d.appearance) for d in detections] for t in tracks])
        known = ~np.isnan(colours)
        cost = distance + self.colour_weight * np.where(known, colours, 0.0)
        allowed = (distance <= self.max_distance) & ~(known & (colours > self.max_colour_distance))
        cost = np.where(allowed, cost, _NO_MATCH)
        if reidentify and self.reid_colour_distance is not None:
            track_size = np.array([[t.size] for t in tracks])
            detection_size = np.array([[max(d.box[2] - d.box[0], d.box[3] - d.box[1], 1.0) for d in detections]])
            alike = np.maximum(track_size / detection_size, detection_size / track_size) <= 1.5
            again = known & (colours <= self.reid_colour_distance) & alike & (cost >= _NO_MATCH)
            cost = np.where(again, self.max_distance + self.colour_weight + colours, cost)  # after every match by position
        if reidentify and self.proportion_tolerance is not None:
            shapes = [body_proportions(d.keypoints, d.confidence) for d in detections]
            for i, track in enumerate(tracks):
                for j, shape in enumerate(shapes):
                    difference = proportion_difference(track.proportions, shape)
                    if cost[i, j] == _NO_MATCH and difference <= self.proportion_tolerance:
                        cost[i, j] = self.max_distance + difference  # after every match by position
        return cost
