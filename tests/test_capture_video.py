"""Video frames in and out (humotion.io.video) and skeleton overlays, on a real CC0 photo and bad files."""

from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from humotion.capture.detection import KEYPOINTS, Detection
from humotion.capture.overlay import draw_people, person_color
from humotion.capture.people import PeopleTracker, TrackedPerson
from humotion.io import MotionFileError
from humotion.io.video import FrameSource, VideoSourceError, VideoWriter, open_frames

PHOTOS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "images" / "yogait_cc0"


@pytest.fixture(scope="module")
def photo() -> Path:
    path = PHOTOS / "y_y1.jpg"
    if not path.is_file():
        pytest.skip(f"real photos not found at {PHOTOS}")
    return path


@pytest.fixture(scope="module")
def photo_detection(photo) -> tuple[np.ndarray, Detection]:
    """The photo at half size (360 x 540) and the one person MediaPipe finds in it."""
    from humotion.capture import MediaPipePoseDetector

    with open_frames(photo) as source:
        (frame,) = list(source)
    image = cv2.resize(frame.image, (540, 360), interpolation=cv2.INTER_AREA)
    with MediaPipePoseDetector(max_people=1) as detector:
        (detection,) = detector.detect(image)
    return image, detection


def test_still_image_is_one_frame(photo):
    with open_frames(photo) as source:
        assert isinstance(source, FrameSource) and len(source) == 1 and source.fps is None
        frames = list(source)
    assert len(frames) == 1
    index, timestamp, image = frames[0]
    assert (index, timestamp) == (0, 0.0) and image.dtype == np.uint8 and image.shape == (720, 1080, 3)
    assert source.size == (1080, 720)
    bgr = cv2.imread(str(photo))
    assert np.array_equal(image, bgr[..., ::-1])  # RGB order
    with pytest.raises(RuntimeError, match="only once"):
        list(source)


def test_overlay_video_round_trip(tmp_path, photo_detection):
    image, detection = photo_detection
    tracker = PeopleTracker()
    path, fps, frames = tmp_path / "out" / "overlay.mp4", 25.0, []
    with VideoWriter(path, fps) as writer:
        for i in range(12):  # the photo panning right 4 px per frame, the detection with it
            shift = np.array([4.0 * i, 0.0], np.float32)
            moved = Detection(detection.keypoints + shift, detection.confidence, detection.score, detection.box)
            people = tracker.update([moved], i / fps)
            assert [p.id for p in people] == [0]
            frames.append(draw_people(np.roll(image, 4 * i, axis=1), people))
            writer.write(frames[-1])
    assert writer.frames_written == 12
    with open_frames(path) as source:
        assert len(source) == 12 and source.size == (540, 360) and source.fps == pytest.approx(fps)
        read = list(source)
    assert [f.index for f in read] == list(range(12))
    assert np.allclose([f.timestamp for f in read], np.arange(12) / fps, atol=1e-3)
    for written, (_, _, back) in zip(frames, read):
        assert back.shape == (360, 540, 3)
        assert np.abs(back.astype(int) - written).mean() < 8  # lossy codec, same picture
    skeleton = (frames[0] == person_color(0)).all(-1)
    x0, y0, x1, y1 = (int(v) for v in detection.box)
    near_person = skeleton[max(y0 - 30, 0):y1 + 10, max(x0 - 10, 0):x1 + 10]  # the id label sits above
    assert skeleton.sum() > 1000 and near_person.sum() == skeleton.sum()


def test_overlay_draws_confident_keypoints_only():
    canvas = np.zeros((200, 300, 3), np.uint8)
    keypoints = np.column_stack([np.linspace(20, 280, len(KEYPOINTS)), np.full(len(KEYPOINTS), 100.0)])
    confidence = np.ones(len(KEYPOINTS), np.float32)
    confidence[10:] = 0.1
    person = TrackedPerson(3, keypoints.astype(np.float32), confidence, None)
    drawn = draw_people(canvas, [person], min_confidence=0.3)
    assert not canvas.any()  # a new array; the input is untouched
    colored = (drawn == person_color(3)).all(-1)
    assert colored[95:106, 15:25].any()  # first keypoint drawn
    assert not drawn[90:110, int(keypoints[15, 0]) - 3:int(keypoints[15, 0]) + 3].any()  # unconfident: not drawn
    assert (drawn[:95] == 255).all(-1).any()  # the white label text above the person


def test_writer_keeps_frames_written_before_a_failure(tmp_path):
    path = tmp_path / "partial.mp4"
    with pytest.raises(KeyError):
        with VideoWriter(path, 10.0) as writer:
            for value in (0, 100, 200):
                writer.write(np.full((48, 64, 3), value, np.uint8))
            raise KeyError("the caller failed midway")
    with open_frames(path) as source:
        means = [frame.image.mean() for frame in source]
    assert len(means) == 3 and np.allclose(means, [0, 100, 200], atol=4)
    with pytest.raises(RuntimeError, match="closed"):
        writer.write(np.zeros((48, 64, 3), np.uint8))


def test_writer_makes_h264_that_keeps_odd_sized_frames(tmp_path):
    path = tmp_path / "odd.mp4"
    image = np.zeros((47, 63, 3), np.uint8)
    image[:, :31] = 200                     # bright left half, dark right half
    with VideoWriter(path, 24.0) as writer:
        for _ in range(5):
            writer.write(image)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"   # browsers play it; mp4v they do not
        assert (stream.width, stream.height) == (64, 48)   # padded to even sides
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
    assert len(frames) == 5
    assert abs(frames[0][:47, :63].astype(int) - image).mean() < 8


def test_writer_names_an_unknown_codec():
    with pytest.raises(ValueError, match="'h265x'"):
        VideoWriter("never.mp4", 10.0, codec="h265x")


def test_writer_rejects_a_frame_of_another_size(tmp_path):
    with VideoWriter(tmp_path / "v.mp4", 10.0) as writer:
        writer.write(np.zeros((48, 64, 3), np.uint8))
        with pytest.raises(ValueError, match="64x48"):
            writer.write(np.zeros((50, 64, 3), np.uint8))


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("missing.mp4", None, "file not found"),
        ("empty.mp4", b"", "file is empty"),
        ("corrupt.mp4", np.random.default_rng(0).bytes(20000), "cannot decode as a video"),
        ("corrupt.png", b"\x89PNG\r\n\x1a\n" + bytes(100), "cannot decode the image"),
        ("drawing.svg", b"<svg xmlns='http://www.w3.org/2000/svg'/>", "unsupported image format '.svg'"),
    ],
)
def test_bad_files_name_the_file_and_the_problem(tmp_path, name, content, problem):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(VideoSourceError, match=problem) as error:
        open_frames(path)
    assert str(path) in str(error.value) and isinstance(error.value, MotionFileError)


def test_video_without_frames(tmp_path):
    path = tmp_path / "no_frames.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    writer.release()  # a valid AVI container holding no frame
    with pytest.raises(VideoSourceError, match="no frames") as error:
        open_frames(path)
    assert str(path) in str(error.value)


def test_missing_camera():
    with pytest.raises(VideoSourceError, match="camera 97"):
        open_frames(97)
