"""People in a video, frame by frame: a pose detector and the tracker, with a scan spread over frames.

A detector that can look at parts of the frame (`humotion.capture.movenet.MoveNetDetector`: it has
`detect_regions` and `detect_near`) is used top-down, which keeps the cost per frame low and flat:

1. the people the tracker saw in the last frames are looked for on a crop around where their
   velocity puts them (`PeopleTracker.predicted_boxes`, `detect_near`): one small model run each.
   Each person seen in the previous frame gets that run on every `detect_every`-th frame only
   (people taken in turn, so each frame runs a share of them); in between, their keypoints are
   carried from the previous frame by pyramidal Lucas-Kanade optical flow (OpenCV), checked
   forwards and backwards, when frames come at most `MAX_FLOW_STEP` apart (at 640x480 the flow
   costs about 1 ms a frame plus 0.6 ms a person, against about 8 ms a person for the model);
2. `regions_per_frame` of the full scan's regions (`scan_regions`: the whole frame and tiles) are
   searched in turn, so the whole frame is covered every few frames; people found there who are
   no one already followed are refined on a crop of their own and added. The first frame (and
   the first after the frame size changes) is searched in every region at once, as a photo is:
   everyone in view from the start is followed from the start;
3. each person gets their torso colours (`humotion.capture.people.torso_histogram`), and the
   tracker gives them their ids.

Any other `PoseDetector` runs on the whole frame each time, and its people go to the tracker.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from humotion.capture.detection import MAX_PEOPLE, Detection, PoseDetector, keypoint_box
from humotion.capture.people import PeopleTracker, TrackedPerson, torso_histogram


SCAN_INTERVAL = 0.1
"""Seconds, default of PeopleFinder's scan_interval: every third frame at 30 fps, every frame at
10 fps. Counted in seconds, not frames, so that a low frame rate does not make newcomers wait
longer (the capture model card and docs/capture.md have the bench runs behind it)."""

DETECT_EVERY = 2
"""Default of PeopleFinder's detect_every: a followed person's pose model runs on every other
frame, optical flow carries their keypoints in between (bench/capture_speed.py, bench/capture_people.py)."""

MAX_FLOW_STEP = 0.05
"""Seconds: optical flow carries keypoints only between frames this close (20 fps or more); at
lower frame rates people move too far between frames and every frame runs the model."""

_FLOW_WINDOW = (15, 15)  # pixels: Lucas-Kanade window at each pyramid level
_FLOW_AGREEMENT = 0.03  # a point whose forward-backward flow misses its start by more (of the person's size) is lost
_FLOW_MIN_POINTS = 8  # fewer points carried: the person is detected by the model instead


class PeopleFinder:
    """detector + tracker for video frames; see the module docstring.

    regions_per_frame: scan regions searched per scanned frame (a MoveNet MultiPose run each); more
        finds newcomers sooner and costs more per frame.
    scan_interval: while someone is followed, the scan runs on a frame at least this many seconds
        after the last scan only (with nobody followed, on every frame); more lowers the cost per
        frame and finds newcomers later.
    max_people: most people followed at once.
    appearance: give detections their torso colours for the tracker.
    follow_missed: a person is still looked for on a crop this many frames after last being found.
    detect_every: a person seen in the previous frame runs the pose model on every detect_every-th
        frame, optical flow carrying their keypoints in between (1: the model every frame).
    """

    def __init__(self, detector: PoseDetector, tracker: PeopleTracker, regions_per_frame: int = 1,
                 max_people: int = MAX_PEOPLE, appearance: bool = True, follow_missed: int = 8, scan_interval: float = SCAN_INTERVAL,
                 detect_every: int = DETECT_EVERY):
        if regions_per_frame < 1 or max_people < 1 or detect_every < 1 or not scan_interval >= 0:
            raise ValueError(f"need regions_per_frame, max_people and detect_every >= 1 and scan_interval >= 0, got "
                             f"{regions_per_frame}, {max_people}, {detect_every} and {scan_interval}")
        self.scan_interval, self.detect_every = scan_interval, detect_every
        self._scanned_at = -math.inf  # the time of the last scan, seconds
        self.detector, self.tracker = detector, tracker
        self.regions_per_frame, self.max_people, self.appearance = regions_per_frame, max_people, appearance
        self.follow_missed = follow_missed
        self._next_region = 0
        self._regions: list = []
        self._size: tuple[int, int] | None = None
        self._previous: tuple[np.ndarray, float] | None = None  # the last frame in grey, and its time
        self.timings = {"follow": 0.0, "scan": 0.0, "track": 0.0}  # seconds spent, summed over frames
        self.frames = 0

    @property
    def top_down(self) -> bool:
        """Whether the detector can be run on parts of the frame (detect_regions and detect_near)."""
        return hasattr(self.detector, "detect_regions") and hasattr(self.detector, "detect_near")

    def __call__(self, image: np.ndarray, timestamp: float) -> list[TrackedPerson]:
        """The people of one frame ((H, W, 3) uint8 RGB, timestamp in seconds, increasing), by id."""
        import time

        start = time.perf_counter()
        if not self.top_down:
            detections = self.detector.detect(image)
            scanned = time.perf_counter()
        else:
            detections, scanned = self._top_down(image, timestamp, start)
        if self.appearance:
            detections = [replace(d, appearance=torso_histogram(image, d.keypoints, d.confidence)) for d in detections]
        people = self.tracker.update(detections, timestamp)
        self.timings["track"] += time.perf_counter() - scanned
        self.frames += 1
        return people

    def _top_down(self, image: np.ndarray, timestamp: float, start: float) -> tuple[list[Detection], float]:
        import time

        from humotion.capture.movenet import merge_detections, same_person, scan_regions

        size = (image.shape[1], image.shape[0])
        first = size != self._size
        if first:
            self._size, self._next_region = size, 0
            self._regions = scan_regions(*size, getattr(self.detector, "tile", 256))
        predicted = self.tracker.predicted_boxes(timestamp, self.follow_missed)[: self.max_people]
        carried = self._carried(image, timestamp, [i for i, _ in predicted])
        followed = [d for d in self.detector.detect_near(image, [box for i, box in predicted if i not in carried])
                    if d is not None]
        followed = merge_detections(list(carried.values()) + followed)
        followed_at = time.perf_counter()
        new = []
        if not followed or timestamp - self._scanned_at >= self.scan_interval - 1e-3:   # a millisecond's slack
            self._scanned_at = timestamp
            count = len(self._regions) if first else self.regions_per_frame
            chosen = [self._regions[(self._next_region + k) % len(self._regions)] for k in range(count)]
            self._next_region = (self._next_region + count) % len(self._regions)
            new = [d for d in self.detector.detect_regions(image, chosen)
                   if not any(same_person(d, f) for f in followed)]
        if new:
            new = [d for d in self.detector.refine(image, new) if not any(same_person(d, f) for f in followed)]
        detections = merge_detections(followed + new, first=len(followed))[: self.max_people]
        scanned = time.perf_counter()
        self.timings["follow"] += followed_at - start
        self.timings["scan"] += scanned - followed_at
        return detections, scanned

    def _carried(self, image: np.ndarray, timestamp: float, ids: list[int]) -> dict[int, Detection]:
        """{id: detection} of the people among ids whose keypoints optical flow carries from the
        previous frame to this one (see the module docstring); the others run the model."""
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if self.detect_every > 1 else None
        previous, self._previous = self._previous, (grey, timestamp) if grey is not None else None
        if previous is None or timestamp - previous[1] > MAX_FLOW_STEP or previous[0].shape != grey.shape:
            return {}
        last = self.tracker.last_seen()
        chosen = [i for i in ids if i in last and (self.frames + i) % self.detect_every]
        if not chosen:
            return {}
        start = np.stack([last[i].keypoints for i in chosen]).astype(np.float32)       # (P, 21, 2) pixels
        flow = dict(winSize=_FLOW_WINDOW, maxLevel=3)
        ahead, found, _ = cv2.calcOpticalFlowPyrLK(previous[0], grey, start.reshape(-1, 1, 2), None, **flow)
        back, found_back, _ = cv2.calcOpticalFlowPyrLK(grey, previous[0], ahead, None, **flow)
        ahead, kept = ahead.reshape(start.shape), (found & found_back).reshape(start.shape[:2]) == 1
        miss = np.linalg.norm(back.reshape(start.shape) - start, axis=-1)                # (P, 21) pixels
        carried = {}
        for k, i in enumerate(chosen):
            x0, y0, x1, y1 = last[i].box
            agree = kept[k] & (miss[k] <= _FLOW_AGREEMENT * max(x1 - x0, y1 - y0, 1.0))
            confidence = np.where(agree, last[i].confidence, 0.0).astype(np.float32)
            if (confidence >= 0.3).sum() >= _FLOW_MIN_POINTS:
                carried[i] = Detection(ahead[k], confidence, last[i].score, keypoint_box(ahead[k], confidence, 0.2))
        return carried


DETECTORS: tuple[str, ...] = ("movenet", "mediapipe")
"""Names `make_detector` knows: "movenet" (the default: everyone in the frame, small people too;
humotion.capture.movenet) and "mediapipe" (BlazePose, for one person who fills the frame; the
earlier default, humotion.capture.detection.MediaPipePoseDetector)."""


def make_detector(name: str = "movenet", max_people: int = MAX_PEOPLE) -> PoseDetector:
    """The pose detector called name (see DETECTORS), reporting at most max_people people."""
    if name == "movenet":
        from humotion.capture.movenet import MoveNetDetector

        return MoveNetDetector(max_people=max_people)
    if name == "mediapipe":
        from humotion.capture.detection import MediaPipePoseDetector

        return MediaPipePoseDetector(max_people=max_people)
    raise ValueError(f"unknown detector {name!r}: choose one of {', '.join(DETECTORS)}")
