"""Video capture end to end (specs/video-capture.md): frames -> 2D people -> 3D motion per person.

    result = capture("clip.mp4", "out/")                # files per person, JSON, overlay video

Stages, per frame: detection (humotion.capture.detection), tracking with stable ids and One-Euro
smoothing (humotion.capture.people), the overlay video (an image for a still image); then per
person and per stretch of frames in which they were seen without a break (a segment): lifting to
3D (humotion.capture.lifting) at the lifter's frame rate, scaling to the template by height
(given, the default, or with CaptureConfig.height_reference estimated relative to a reference
person from everyone's floor contacts in a first pass: humotion.capture.height) and bone-length
correction, joint angles (humotion.capture.joint_angles) and the initial root from reprojection
alone. Then, from everyone at once, the camera (humotion.capture.camera): its pitch, roll and
height over one floor, assuming a static camera (given values win), each person's systematic
tilt from the lifter straightened to that floor's vertical; then per person the refinement
(humotion.capture.refine) with planted feet held on the floor, and the files, written as each
person finishes.

World frame of the results: one for everyone (humotion.capture.camera.CameraPose): Y up, the floor
at y = 0, the camera at (0, camera height, 0) looking along -Z, pitched and rolled as estimated.
A person facing the camera faces +Z. capture.json states the camera's intrinsics and pose, so its
3D points project onto their own 2D keypoints.

Interruptions: Ctrl-C (KeyboardInterrupt) or an error during the 3D stage keeps every person's
files already written, and capture.json is written (atomically) for the people finished; Ctrl-C
returns with CaptureResult.interrupted set, an error is raised again after writing.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

from humotion import rotations as rot
from humotion.canonical import JOINTS
from humotion.capture.camera import (SOLES, CameraPose, contact_soles, estimate_camera, floor_drift, still_soles,
                                     tilt_correction)
from humotion.capture.detection import KEYPOINTS, MAX_PEOPLE, PoseDetector
from humotion.capture.follow import PeopleFinder, make_detector
from humotion.capture.filters import OneEuroConfig
from humotion.capture.height import FloorContacts, contacts_of, estimate_heights
from humotion.capture.joint_angles import correct_bone_lengths, positions_to_rotations
from humotion.capture.keypoints import VirtualCamera, body_keypoints_3d
from humotion.capture.lifting import Lifter, lift_sequence, load_lifter, person_centred
from humotion.capture.metrology import camera_from_people
from humotion.capture.overlay import draw_people
from humotion.capture.people import PeopleTracker, TrackedPerson
from humotion.capture.prior import PosePrior
from humotion.capture.refine import CaptureRefineConfig, initial_root, refine_capture
from humotion.capture.template import DEFAULT_HEIGHT, template_skeleton
from humotion.io import save_motion
from humotion.io.errors import MotionFileError, OutputPathError
from humotion.io.paths import write_atomic
from humotion.io.video import FrameSource, VideoWriter, open_frames
from humotion.motion import Motion
from humotion.skeleton import Skeleton, forward_kinematics


@dataclass
class CaptureConfig:
    """The settings of one capture (each field's docstring is its command-line help too)."""

    height_m: float = DEFAULT_HEIGHT
    """Everyone's standing height, metres (the template's); humotion.capture.template.typical_height
    gives one by sex and age."""
    heights: dict[int, float] = field(default_factory=dict)
    """{person id: metres} for people of another height (ids as in the results: 0, 1, ... in order
    of appearance)."""
    hfov_deg: float = 60.0
    """Camera's horizontal field of view, degrees (principal point at the image centre)."""
    focal_px: float | None = None
    """Camera's focal length in pixels; wins over hfov_deg when given."""
    max_people: int = MAX_PEOPLE
    """Most people followed at once."""
    detector: str = "movenet"
    """2D pose detector (humotion.capture.follow.DETECTORS): movenet finds everyone in the frame from
    about 50 px tall (MoveNet MultiPose + Lightning, top-down); mediapipe (BlazePose) suits one
    person who fills the frame."""
    min_frames: int = 3
    """A person's stretches shorter than this many frames are dropped."""
    filter: OneEuroConfig = field(default_factory=OneEuroConfig)
    """One-Euro smoothing of the 2D keypoints."""
    refine: CaptureRefineConfig | None = field(default_factory=CaptureRefineConfig)
    """The refinement (humotion.capture.refine; None: skipped, faster and less accurate)."""
    body: str | None = None
    """Also write each person on the learned body model (personN_body.glb: a skinned body of their
    height, humotion.body), at this mesh resolution: "low" or "full" (unset: skeletons only)."""
    height_reference: int | None = None
    """A person id whose height is in heights: everyone else without one gets a height estimated
    relative to theirs, all on one flat floor seen by a static camera (humotion.capture.height;
    about 10% error); a person it cannot be estimated for keeps height_m, with a warning (unset:
    no estimation)."""
    pitch_deg: float | None = None
    """The camera's pitch below the horizon, degrees, when known (roll taken as 0; unset: estimated
    from the people, humotion.capture.camera)."""
    camera_height: float | None = None
    """The camera's height above the floor, metres, when known (unset: estimated from the people, a
    static camera assumed; humotion.capture.camera)."""

    def __post_init__(self):  # checked before any frame is read
        if self.body not in (None, "low", "full"):
            raise ValueError(f"body must be 'low', 'full' or None, got {self.body!r}")
        if self.height_reference is not None and self.height_reference not in self.heights:
            raise ValueError(f"the height reference, person {self.height_reference}, needs a given height "
                             f"(--height {self.height_reference}=METRES, or heights={{{self.height_reference}: metres}})")
        for height in (self.height_m, *self.heights.values()):
            template_skeleton(height)
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"hfov_deg must be a field of view in degrees between 1 and 170, got {self.hfov_deg}")
        if self.focal_px is not None and not self.focal_px > 0:
            raise ValueError(f"focal_px must be a positive focal length in pixels, got {self.focal_px}")
        if self.pitch_deg is not None and not -90.0 < self.pitch_deg < 90.0:
            raise ValueError(f"pitch_deg must be degrees below the horizon between -90 and 90, got {self.pitch_deg}")
        if self.camera_height is not None and not 0.0 < self.camera_height < 100.0:
            raise ValueError(f"camera_height must be metres above the floor between 0 and 100, got {self.camera_height}")


    def height_of(self, person: int) -> float:
        """The standing height (metres) of the person with this id."""
        return self.heights.get(person, self.height_m)


def default_camera(width: int, height: int, hfov_deg: float = 60.0, focal_px: float | None = None) -> VirtualCamera:
    """Intrinsics of a camera with square pixels and the principal point at the image centre."""
    focal = focal_px if focal_px is not None else width / 2 / math.tan(math.radians(hfov_deg) / 2)
    return VirtualCamera(focal, focal, width / 2, height / 2, width, height, torch.eye(3), torch.zeros(3))


@dataclass
class Segment:
    """One person seen on consecutive frames: frames (T,) int64 indices, times (T,) float64
    seconds, keypoints (T, 21, 2) float32 pixels, confidence (T, 21) float32. Array-likes
    (numpy arrays, lists) are converted to tensors of these dtypes; ValueError on other shapes."""

    person: int
    frames: torch.Tensor
    times: torch.Tensor
    keypoints: torch.Tensor
    confidence: torch.Tensor

    def __post_init__(self):
        self.frames = torch.as_tensor(self.frames, dtype=torch.int64)
        self.times = torch.as_tensor(self.times, dtype=torch.float64)   # float32 steps by 0.24 ms an hour in
        self.keypoints = torch.as_tensor(self.keypoints, dtype=torch.float32)
        self.confidence = torch.as_tensor(self.confidence, dtype=torch.float32)
        t, k = (len(self.frames) if self.frames.ndim else 0), len(KEYPOINTS)
        for name, shape in (("frames", (t,)), ("times", (t,)), ("keypoints", (t, k, 2)), ("confidence", (t, k))):
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"Segment.{name} has shape {tuple(getattr(self, name).shape)}, expected "
                                 f"{shape} (T = {t} frames, {k} keypoints)")


@dataclass
class PersonMotion:
    """A segment's result: the motion (world frame, template skeleton), joints (T, 22, 3) and the
    detector's keypoints on the body, keypoints (T, 21, 3), metres."""

    segment: Segment
    motion: Motion
    joints: torch.Tensor
    keypoints: torch.Tensor | None = None


@dataclass
class TrackedVideo:
    """What track_video saw. people: {person id: [(frame index, time s, keypoints (21, 2) pixels,
    confidence (21,)), ...]} in frame order; fps: the source's frame rate, or for a camera the rate
    frames were processed at; size: (width, height) pixels; frames: how many were read; warnings:
    one line each (a read error midway, Ctrl-C)."""

    people: dict[int, list]
    fps: float
    size: tuple[int, int]
    frames: int
    warnings: list[str]


def track_video(frames: FrameSource, detector: PoseDetector, tracker: PeopleTracker, overlay: Path | None = None,
                progress: bool = True, on_frame: Callable[[np.ndarray, list[TrackedPerson]], None] | None = None,
                background: list[float] | None = None) -> TrackedVideo:
    """Detect and track people on every frame of an opened source (humotion.io.video.open_frames).
    on_frame(image, people) is called after each frame with the (H, W, 3) uint8 RGB image (the
    overlay drawn on it when overlay is given), e.g. by live capture. overlay: a video path, or an
    image path (.png, .jpg) where the last frame's drawing is written (a still image). background: when given, the
    image's shift from the previous frame (pixels, phase correlation of the whole frame, mostly
    background) is appended for every frame after the first: a static camera gives about 0.

    A read error midway ends the video there (a warning) and what came before is kept, as on
    Ctrl-C; the overlay (when a path is given) is finalised in every case.
    """
    people: dict[int, list] = {}
    warnings: list[str] = []
    times: list[float] = []
    fps, size = float(frames.fps or 30.0), frames.size
    still = overlay is not None and overlay.suffix.lower() in (".png", ".jpg")
    writer = VideoWriter(overlay, fps) if overlay and not still else None
    bar = tqdm(total=frames.frame_count, desc="detecting people", unit="frame", disable=not progress)
    finder = PeopleFinder(detector, tracker)   # top-down with a detector that can, whole frames otherwise
    stream = iter(frames)
    drawn, previous = None, None
    try:
        while True:
            try:
                index, time, image = next(stream)
            except StopIteration:
                break
            except MotionFileError as error:        # reading failed; writing the overlay may not fail silently
                warnings.append(f"stopped reading: {error}")
                break
            times.append(time)
            tracked = finder(image, time)
            for person in tracked:
                people.setdefault(person.id, []).append((index, time, person.keypoints, person.confidence))
            if background is not None:
                previous = _background_shift(image, previous, background)
            if overlay or on_frame:
                drawn = draw_people(image, tracked)
            if writer:
                writer.write(drawn)
            if on_frame:
                on_frame(drawn, tracked)
            bar.update()
    except KeyboardInterrupt:
        warnings.append("interrupted: the frames read so far are used")
    finally:
        bar.close()
        if writer:
            writer.close()
        if still and drawn is not None:
            _write_image(overlay, drawn)
    if frames.live and len(times) > 1 and times[-1] > times[0]:
        fps = (len(times) - 1) / (times[-1] - times[0])
    return TrackedVideo(people, fps, size, len(times), warnings)


def _background_shift(image: np.ndarray, previous: np.ndarray | None, shifts: list[float]) -> np.ndarray:
    """The frame made small and grey for the next call; appends to shifts its shift from previous
    (pixels of the full image, by phase correlation; nothing for blank or ambiguous frames)."""
    import cv2

    scale = 160 / max(image.shape[:2])
    small = cv2.resize(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None, fx=scale, fy=scale,
                       interpolation=cv2.INTER_AREA).astype(np.float32)
    if previous is not None and previous.shape == small.shape and small.std() > 2.0:
        (dx, dy), response = cv2.phaseCorrelate(previous, small)
        if response > 0.2:          # a clear peak: a textured image (a blank one tells nothing)
            shifts.append(float(math.hypot(dx, dy)) / scale)
    return small


def _write_image(path: Path, image: np.ndarray) -> None:
    """Write an RGB image (H, W, 3) uint8, in the format of path's suffix, atomically
    (humotion.io.paths.write_atomic)."""
    import cv2

    encoded, data = cv2.imencode(path.suffix, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not encoded:
        raise OutputPathError(path, f"cannot encode the image as {path.suffix}")
    write_atomic(path, data.tobytes())


BRIDGED_GAP = 0.25
"""Seconds: a person missed on the frames between two observations this close (a detection lost
for a few frames, a short occlusion) keeps one segment; the missing frames get keypoints
interpolated between the two and half the lower of their confidences."""


def segments_of(person: int, observations: list, min_frames: int, min_confidence: float = 0.2) -> list[Segment]:
    """The person's observations [(frame, time s, keypoints (21, 2), confidence (21,))] as segments:
    cut where frames are missing for longer than BRIDGED_GAP (shorter gaps are filled in, see there)
    or no keypoint reaches min_confidence (nothing to lift there), short segments dropped."""
    observations = [o for o in observations if o[3].max() >= min_confidence]
    frames = np.array([o[0] for o in observations], dtype=int)
    times = np.array([o[1] for o in observations], dtype=float)
    cuts = np.flatnonzero((np.diff(frames) > 1) & (np.diff(times) > BRIDGED_GAP)) + 1
    out = []
    for part in np.split(np.arange(len(frames)), cuts):
        rows = [observations[i] for i in part]
        filled = [rows[0]] if rows else []
        for before, after in zip(rows, rows[1:]):
            for frame in range(before[0] + 1, after[0]):                       # a bridged gap
                w = (frame - before[0]) / (after[0] - before[0])
                filled.append((frame, (1 - w) * before[1] + w * after[1], (1 - w) * before[2] + w * after[2],
                               0.5 * np.minimum(before[3], after[3])))
            filled.append(after)
        if len(filled) >= min_frames:
            out.append(Segment(person, np.array([o[0] for o in filled]), np.array([o[1] for o in filled]),
                               np.stack([o[2] for o in filled]), np.stack([o[3] for o in filled])))
    return out


def lift_segment(lifter: Lifter, segment: Segment, camera: VirtualCamera) -> torch.Tensor:
    """(T, 22, 3) the lifter's joints (pelvis-relative, camera axes, units of height) on the
    segment's frames. The lifter sees the keypoints as a camera turned to look at the person would
    (person_centred), as its training cameras did, and its joints are turned back into camera's
    axes. The 2D track is resampled on its timestamps to the lifter's rate and the result back
    (linear), unless the frames already come at that rate."""
    keypoints, turn = person_centred(segment.keypoints, segment.confidence, camera)
    times = (segment.times - segment.times[0]).numpy()      # np.interp's, in _interpolate
    if len(times) < 2 or abs((len(times) - 1) / times[-1] - lifter.fps) < 0.5:
        joints = lift_sequence(lifter, keypoints, segment.confidence)
    else:
        grid = np.arange(0.0, times[-1] + 1e-9, 1.0 / lifter.fps)
        joints = lift_sequence(lifter, _interpolate(times, keypoints, grid),
                               _interpolate(times, segment.confidence, grid))
        joints = _interpolate(grid, joints, times)
    return joints @ turn        # each frame's R^T j: back to the camera's axes


def _interpolate(times: np.ndarray, values: torch.Tensor, new_times: np.ndarray) -> torch.Tensor:
    """values (T, ...) at times, linearly interpolated at new_times (clamped at the ends)."""
    flat = values.reshape(len(values), -1).numpy()
    out = np.stack([np.interp(new_times, times, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return torch.as_tensor(out, dtype=torch.float32).reshape((len(new_times),) + values.shape[1:])


@dataclass
class CameraFrameFit:
    """One segment in the camera frame: rotations (T, 22, 3) rotation vectors (joint 0 global),
    root (T, 3) metres, on skeleton; network (T, 22, 3) the lifter's joints after bone-length
    correction and lifted (T, 22, 3) before it (both pelvis-relative, metres)."""

    rotations: torch.Tensor
    root: torch.Tensor
    skeleton: Skeleton
    network: torch.Tensor
    lifted: torch.Tensor


def initial_fit(segment: Segment, camera: VirtualCamera, lifter: Lifter, height_m: float,
                unit_lift: torch.Tensor | None = None) -> CameraFrameFit:
    """Steps 3-7 of the spec for one segment: lifting, the template at height_m, bone-length
    correction, joint angles, and the root track placed by reprojection (template_fit). unit_lift:
    (T, 22, 3) the segment's lift_segment(lifter, segment, camera) when already at hand (in units of
    height: it does not depend on height_m)."""
    lifted = (lift_segment(lifter, segment, camera) if unit_lift is None else unit_lift) * height_m
    return template_fit(lifted, template_skeleton(height_m), segment, camera)


def template_fit(lifted: torch.Tensor, skeleton: Skeleton, segment: Segment, camera: VirtualCamera) -> CameraFrameFit:
    """Steps 6-7 and the initial root: lifted (T, 22, 3) joints (pelvis-relative, camera axes,
    metres) corrected to skeleton's bone lengths and turned into joint angles; the root track
    placed so the body's keypoints best reproject onto the segment's, with a smooth depth
    (humotion.capture.refine.initial_root on the segment's timestamps)."""
    network = correct_bone_lengths(lifted, skeleton)      # the pelvis stays at 0
    quats, _ = positions_to_rotations(network, skeleton)
    world_r, joints = forward_kinematics(quats, torch.zeros(len(quats), 3), skeleton.offsets, skeleton.parents)
    root = initial_root(body_keypoints_3d(world_r, joints, skeleton), segment.keypoints, segment.confidence,
                        camera, segment.times)
    return CameraFrameFit(rot.convert(quats, "quat", "rotvec"), root, skeleton, network, lifted)


def refined(fit: CameraFrameFit, segment: Segment, camera: VirtualCamera, prior: PosePrior,
            config: CaptureRefineConfig, pose: CameraPose | None = None, fps: float = 30.0) -> CameraFrameFit:
    """Step 8: the fit refined against the segment's detections (humotion.capture.refine). With
    the camera's pose, feet are held, in two passes: the first with the soles found on the fit,
    the second with those found on the first's result (feet found again once on the floor).
    Planted soles (low and slow in 3D: humotion.capture.camera.contact_soles, at fps) are held on
    the floor without sliding; soles still in the image (low, their pixels still: still_soles,
    which the lifter's depth cannot hide) without sliding, the floor not forced on them."""
    passes = 1 if pose is None or not (config.floor or config.skate) else 2
    for _ in range(passes):
        floor = planted = still = None
        if pose is not None:
            _, points = fit_points(fit)
            floor = (pose.up, pose.height)
            planted = contact_soles(points[:, SOLES], pose.up, fps)
            still = still_soles(segment.keypoints, segment.confidence, segment.times, points[:, SOLES], pose.up,
                                float(camera.fx), config.still_speed)
        rotations, root = refine_capture(fit.rotations, fit.root, fit.skeleton, camera, segment.keypoints,
                                         segment.confidence, fit.network, prior, config, floor, planted, still)
        fit = CameraFrameFit(rotations, root, fit.skeleton, fit.network, fit.lifted)
    return fit


def fit_points(fit: CameraFrameFit) -> tuple[torch.Tensor, torch.Tensor]:
    """(joints (T, 22, 3), body keypoints (T, 21, 3)) of a fit, camera frame, metres."""
    world_r, joints = forward_kinematics(rot.convert(fit.rotations, "rotvec", "matrix"), fit.root,
                                         fit.skeleton.offsets, fit.skeleton.parents)
    return joints, body_keypoints_3d(world_r, joints, fit.skeleton)


def straightened(fit: CameraFrameFit, segment: Segment, camera: VirtualCamera, pose: CameraPose) -> CameraFrameFit:
    """The fit with the person's systematic tilt taken out: the lifter's joints turned about the
    pelvis so that the person's median standing axis is the floor's vertical
    (humotion.capture.camera.tilt_correction; unchanged when they never stand), then corrected
    and placed again (template_fit)."""
    joints, _ = fit_points(fit)
    turn = tilt_correction(joints - fit.root[:, None], pose.up)
    if torch.allclose(turn, torch.eye(3)):
        return fit
    return template_fit(fit.lifted @ turn.T, fit.skeleton, segment, camera)


def to_world(fit: CameraFrameFit, segment: Segment, fps: float, pose: CameraPose) -> PersonMotion:
    """A camera-frame fit as a motion in the world frame of the module docstring."""
    turn, shift = pose.world_from_camera()
    rotations = rot.convert(fit.rotations, "rotvec", "matrix")
    rotations[:, 0] = turn @ rotations[:, 0]
    root = fit.root @ turn.T + shift
    world_r, joints = forward_kinematics(rotations, root, fit.skeleton.offsets, fit.skeleton.parents)
    motion = Motion(fit.skeleton, rot.matrix_to_quat(rotations), root, fps, name=f"person{segment.person}")
    return PersonMotion(segment, motion, joints, body_keypoints_3d(world_r, joints, fit.skeleton))


def camera_pose(fits: list[CameraFrameFit], segments: list[Segment], fps: float, config: CaptureConfig,
                warnings: list[str], shifts: list[float] | None = None, width: int = 640,
                camera: VirtualCamera | None = None) -> CameraPose:
    """The static camera's pose from everyone's upright frames in the image (with the camera's
    intrinsics: humotion.capture.metrology) or else their initial fits (humotion.capture.camera.estimate_camera),
    with warnings appended where the camera seems to move (the floor's distance drifting between
    time windows, or the background shifting by over 0.1% of the image width per frame, median:
    a hand-held camera shifts its image by 0.2%, a fixed one by 0.01%, on the shared real videos)."""
    points = [fit_points(fit) for fit in fits]
    soles = [k[:, SOLES] for _, k in points]
    image_pose = None
    if camera is not None and config.pitch_deg is None:
        image_pose = camera_from_people([s.keypoints.numpy() for s in segments],      # numpy and scipy there
                                        [s.confidence.numpy() for s in segments],
                                        [config.height_of(s.person) for s in segments], camera)
    pose = estimate_camera([j for j, _ in points], [k for _, k in points], fps, config.pitch_deg, config.camera_height,
                           image_pose=image_pose)
    if config.camera_height is not None and fits:
        fitted = estimate_camera([j for j, _ in points], [k for _, k in points], fps, config.pitch_deg,
                                 image_pose=image_pose).height
        if abs(fitted - config.camera_height) > 0.15 * config.camera_height:
            warnings.append(f"the people's feet put the floor {fitted:.2f} m below the camera, the given camera height "
                            f"is {config.camera_height:.2f} m: their heights (--height) may be off by that ratio")
    drift = floor_drift(pose, soles, [s.times for s in segments], fps)
    if drift is not None and drift > max(0.15 * pose.height, 0.2):
        warnings.append(f"the floor's distance from the camera changes by {drift:.2f} m over the video: a moving "
                        "camera? The results assume a static camera (one floor, one pose)")
    if shifts and len(shifts) >= 5 and float(np.median(shifts)) > 0.001 * width:
        warnings.append(f"the background moves by {float(np.median(shifts)):.1f} px per frame (median): a moving "
                        "camera? The results assume a static camera (one floor, one pose)")
    if pose.source == "level" and fits:
        warnings.append(f"nobody stood or touched the floor: the camera is taken as level, {pose.height:.2f} m high")
    return pose


@dataclass
class CaptureResult:
    """What capture() made: people's motions, the files written, warnings, the camera's pose
    (None when stopped before it was found) and why the run stopped early (None: it did not)."""

    people: list[PersonMotion]
    files: list[Path]
    warnings: list[str]
    estimated_heights: dict[int, float] = field(default_factory=dict)
    camera: CameraPose | None = None
    interrupted: str | None = None


def capture(source, out_dir: str | Path, config: CaptureConfig = CaptureConfig(), detector: PoseDetector | None = None,
            lifter: Lifter | None = None, prior: PosePrior | None = None, progress: bool = True,
            live_view=None) -> CaptureResult:
    """Run the whole pipeline on a video file, an image or a camera index; write into out_dir:
    person<ID>[_<k>].bvh and .glb per segment (each as soon as it is done), capture.json (the
    camera's intrinsics and pose; per frame 2D keypoints in pixels with confidences, 3D joints and
    3D keypoints in metres, keyed by name; the reprojection error) and overlay.mp4 (overlay.png
    for a still image).
    live_view: a humotion.viewer.live.LiveView that shows everyone in 3D while frames are read
    (humotion.capture.live: causal lifting, no refinement); the files are made as without it.
    Ctrl-C during the 3D stage returns what was finished, with result.interrupted set; an error
    there is raised after capture.json is written for what was finished. Ctrl-C while a file's
    frames are read goes on with the frames read, result.interrupted set too (for a camera it
    is the way to stop, not an interruption). Prints nothing: its warnings are result.warnings
    (and capture.json's), for the caller to show."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lifter, prior = lifter or load_lifter(), prior or PosePrior.load()
    shifts: list[float] = []
    with open_frames(source) as frames:     # a bad source fails here, before the detector loads
        still, live = frames.frame_count == 1 and not frames.live, frames.live
        overlay = out / ("overlay.png" if still else "overlay.mp4")
        detector = detector or make_detector(config.detector, config.max_people)
        camera = default_camera(*frames.size, config.hfov_deg, config.focal_px)
        tracked = track_video(frames, detector, PeopleTracker(filter_config=config.filter), overlay, progress,
                              _live_updates(live_view, camera, config), shifts)
    fps, warnings = tracked.fps, tracked.warnings
    segments = [s for person, obs in sorted(tracked.people.items())
                for s in segments_of(person, obs, min(config.min_frames, tracked.frames))]
    if not segments:
        warnings.append("nobody was found on enough consecutive frames" if tracked.people else "nobody was found")
    result = CaptureResult([], [overlay] if overlay.exists() else [], warnings)
    if not live and any(w.startswith("interrupted") for w in warnings):   # Ctrl-C ends a camera, not a file
        result.interrupted = "interrupted (Ctrl-C) while reading frames: the frames read so far were used"
    try:
        unit_lifts = [lift_segment(lifter, segment, camera) for segment in segments]   # once each, for every pass
        if config.height_reference is not None and segments:
            result.estimated_heights = estimate_people_heights(segments, camera, lifter, config, warnings, unit_lifts)
            config = replace(config, heights={**result.estimated_heights, **config.heights})
        body = _load_body(config.body, warnings) if config.body else None
        fits = [initial_fit(segment, camera, lifter, config.height_of(segment.person), unit_lift)
                for segment, unit_lift in zip(segments, unit_lifts)]
        result.camera = pose = camera_pose(fits, segments, fps, config, warnings, shifts, tracked.size[0], camera)
        for segment, fit in tqdm(zip(segments, fits), total=len(segments), desc="3D per person",
                                 unit="segment", disable=not progress or not segments):
            fit = straightened(fit, segment, camera, pose)
            if config.refine is not None:
                fit = refined(fit, segment, camera, prior, config.refine, None if pose.source == "level" else pose, fps)
            person = to_world(fit, segment, fps, pose)
            stem = f"person{segment.person}" + ("" if _first_of(segment, segments) else f"_{int(segment.frames[0])}")
            for suffix in (".bvh", ".glb"):
                save_motion(person.motion, out / (stem + suffix))
                result.files.append(out / (stem + suffix))
            if body is not None:
                result.files += _write_body(person.motion, config.height_of(segment.person), out / (stem + "_body.glb"),
                                            body, warnings)
            result.people.append(person)
    except KeyboardInterrupt:
        result.interrupted = "interrupted (Ctrl-C)"
        warnings.append(f"interrupted (Ctrl-C) in the 3D stage: {len(result.people)} of {len(segments)} segments done "
                        "and written")
    except BaseException as error:
        result.interrupted = f"stopped by an error: {error!r}"
        warnings.append(f"stopped by an error in the 3D stage ({error!r}): {len(result.people)} of {len(segments)} "
                        "segments done and written")
        raise
    finally:
        result.files.append(_write_json(out / "capture.json", result.people, fps, tracked.size, camera,
                                        result.camera, config, warnings, result.interrupted))
    return result


def estimate_people_heights(segments: list[Segment], camera: VirtualCamera, lifter: Lifter, config: CaptureConfig,
                            warnings: list[str], unit_lifts: list | None = None) -> dict[int, float]:
    """{person id: standing height in metres} of the people without a given height, estimated
    relative to config.height_reference from everyone's floor contacts in their initial fits
    (humotion.capture.height.estimate_heights). Those it declines are left out, with a warning
    appended to warnings. ValueError when the reference was not seen or never had a foot on
    the floor. unit_lifts: the segments' lift_segment results, when already at hand."""
    parts: dict[int, list[FloorContacts]] = {}
    for segment, unit_lift in zip(segments, unit_lifts or [None] * len(segments)):
        fit = initial_fit(segment, camera, lifter, config.height_of(segment.person), unit_lift)
        parts.setdefault(segment.person, []).append(
            contacts_of(fit.rotations, fit.root, fit.skeleton, segment.confidence))
    contacts = {person: FloorContacts.concat(p) for person, p in parts.items()}
    heights, notes = estimate_heights(contacts, {p: config.height_of(p) for p in contacts}, config.height_reference,
                                      people=[p for p in contacts if p not in config.heights])
    warnings += notes
    return heights


def _live_updates(view, camera: VirtualCamera, config: CaptureConfig):
    """The on_frame callback of track_video that feeds a LiveView, or None without a view."""
    if view is None:
        return None
    from humotion.capture.live import LiveCapture

    live = LiveCapture(camera, config.height_m, heights=config.heights)
    return lambda image, people: view.show(live.update(people), image)


def _load_body(resolution: str, warnings: list[str]):
    """The body model for --body (once per run), or None with a warning when it cannot be loaded."""
    from humotion.body.model import load_body_model

    try:
        return load_body_model(resolution)
    except (ValueError, FileNotFoundError) as error:
        warnings.append(f"no bodies written: {error}")
        return None


def _write_body(motion: Motion, height: float, path: Path, body, warnings: list[str]) -> list[Path]:
    """[path] after writing the motion on a body (humotion.body.BodyModel) of this height, or []
    with a warning when the body model cannot make it (the skeleton files are written either way)."""
    from humotion.body.export import animated_body
    from humotion.io.gltf import write_gltf

    try:
        _, rig_motion, mesh = animated_body(body, height, motion)
        write_gltf(rig_motion, path, mesh=mesh)
        return [path]
    except (ValueError, FileNotFoundError) as error:
        warnings.append(f"{path.name} not written: {error}")
        return []


def _first_of(segment: Segment, segments: list[Segment]) -> bool:
    return next(s for s in segments if s.person == segment.person) is segment


def _write_json(path: Path, people: list[PersonMotion], fps: float, size, camera: VirtualCamera,
                pose: CameraPose | None, config: CaptureConfig, warnings: list[str], interrupted: str | None) -> Path:
    """capture.json (written atomically): the camera (intrinsics; its pose in the
    world, found from the people assuming it is static), per person and frame 2D keypoints
    {name: [x, y, confidence]} in pixels, 3D joints and 3D keypoints {name: [x, y, z]} in metres
    (world frame of the module docstring), and the reprojection error of the 3D keypoints through
    the stated camera (reprojection_px)."""
    cam = {"fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
           "width": int(camera.width), "height": int(camera.height),
           "model": "pinhole, no distortion: pixel = (fx x / z + cx, fy y / z + cy) for the camera-frame point "
                    "(x right, y down, z forward) = rotation_world_to_camera @ (world point - position_m)",
           "assumption": "static: one pose for the whole video"}
    if pose is not None:
        cam.update(pose.describe())
    body = {"fps": fps, "image_size": list(size), "height_m": config.height_m,
            "height_reference": config.height_reference,
            "heights_m": {str(p.segment.person): config.height_of(p.segment.person) for p in people},
            "camera": cam,
            "world": "Y up, metres; floor at y = 0; the camera at camera.position_m, pitched and rolled as stated",
            "reprojection_px": reprojection_error(people, camera, pose),
            "interrupted": interrupted, "warnings": warnings, "people": {}}
    for result in people:
        s = result.segment
        frames = body["people"].setdefault(str(s.person), [])
        # plain lists first: indexing tensors element by element costs microseconds a number
        indices, times = s.frames.tolist(), s.times.tolist()
        keypoints, confidence = s.keypoints.tolist(), s.confidence.tolist()
        joints, points = result.joints.tolist(), result.keypoints.tolist()
        for t in range(len(indices)):
            frames.append({
                "frame": indices[t], "time": times[t],
                "keypoints_2d": {name: [round(keypoints[t][k][0], 2), round(keypoints[t][k][1], 2),
                                        round(confidence[t][k], 3)] for k, name in enumerate(KEYPOINTS)},
                "joints_3d": {name: [round(v, 4) for v in joints[t][j]] for j, name in enumerate(JOINTS)},
                "keypoints_3d": {name: [round(v, 4) for v in points[t][k]] for k, name in enumerate(KEYPOINTS)},
            })
    write_atomic(path, json.dumps(body).encode())
    return path


def reprojection_error(people: list[PersonMotion], camera: VirtualCamera, pose: CameraPose | None,
                       min_confidence: float = 0.5) -> dict:
    """{"median", "p95": pixels, "points": how many}: distances between the detected keypoints
    (confidence >= min_confidence) and the people's 3D keypoints (world frame) projected through
    the camera at the pose; None values when there is nothing to measure."""
    if pose is None or not people:
        return {"median": None, "p95": None, "points": 0}
    world_camera = pose.camera_in_world(camera)
    errors = []
    for person in people:
        projected, _ = world_camera.project(person.keypoints)
        sure = person.segment.confidence >= min_confidence
        distance = (projected - person.segment.keypoints).norm(dim=-1)
        errors.append(distance[sure])
    errors = torch.cat(errors).double()
    if not len(errors):
        return {"median": None, "p95": None, "points": 0}
    return {"median": round(float(errors.median()), 2), "p95": round(float(errors.quantile(0.95)), 2),
            "points": len(errors)}
