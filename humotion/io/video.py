"""Video frames in and out: read a video file, a still image or a live camera; write an overlay video.

Frames are RGB uint8 arrays (H, W, 3), each with its index and timestamp in seconds. Decoding uses OpenCV
(`cv2`, installed with mediapipe), whose FFmpeg build reads the usual containers and codecs (mp4,
mov, avi, mkv, webm, animated gif, ...). OpenCV's pip wheels carry no H.264 *encoder*, so
`VideoWriter` encodes with PyAV, whose wheels bundle FFmpeg with libx264: H.264 in .mp4, which
browsers play too.

Timestamps: a file's come from its container (the presentation time of each frame), a camera's from
the clock when the frame was read (seconds since the source was opened), a still image's is 0.

Native log lines: OpenCV, the FFmpeg inside it and MediaPipe print their own warnings to the
process's stderr ("moov atom not found", "[ WARN:0@0.7] ...", "W0000 ... inference_feedback_manager"),
before and beside humotion's own message. They are hidden (`quiet_native_logs` around each call
into those libraries) unless `show_native_logs(True)`, what `--verbose` does.
"""

from __future__ import annotations

import mimetypes
import os
import sys
import time
import weakref
from contextlib import contextmanager
from fractions import Fraction
from pathlib import Path
from typing import Iterator, NamedTuple

import av
import cv2
import numpy as np

from humotion.io.errors import MotionFileError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff", ".pbm", ".pgm", ".ppm", ".pnm")
"""Still-image files read as a one-frame source. Any other file is decoded as a video (GIF included)."""


def check_image(image: np.ndarray) -> np.ndarray:
    """The image as a C-contiguous (H, W, 3) uint8 array; ValueError naming what it got otherwise."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"expected an (H, W, 3) uint8 RGB numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got dtype {image.dtype}")
    return np.ascontiguousarray(image)



_native_logs_shown = False


def show_native_logs(shown: bool) -> None:
    """Let OpenCV, FFmpeg and MediaPipe print their own log lines (True), or hide them (False, the
    default): OpenCV's own log level is set to warnings or errors, and `quiet_native_logs` blocks
    drop what the libraries write to stderr."""
    global _native_logs_shown
    _native_logs_shown = shown
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING if shown else cv2.utils.logging.LOG_LEVEL_ERROR)


@contextmanager
def quiet_native_logs():
    """Within the block, what native code writes to file descriptor 2 (stderr) is dropped, unless
    show_native_logs(True). FFmpeg's messages and MediaPipe's (absl) log lines go there directly,
    and neither library reads a setting for them (MediaPipe 1.2 ignores GLOG_minloglevel and
    TF_CPP_MIN_LOG_LEVEL). Process-wide while it lasts: other threads' stderr is dropped too, so
    keep the block around the one library call."""
    if _native_logs_shown:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


show_native_logs(False)


class VideoSourceError(MotionFileError):
    """A video, image or camera could not be opened, read or written: names the source and the problem.

    A MotionFileError, so code that reports unreadable input files reports these too.
    """


class Frame(NamedTuple):
    """One frame: index (0, 1, ...), timestamp (seconds), image ((H, W, 3) uint8 RGB)."""

    index: int
    timestamp: float
    image: np.ndarray


class FrameSource:
    """The frames of a video file, a still image or a camera, read once in order; see `open_frames`.

    Iterate for `Frame`s (index, timestamp, image); a file that ends well short of its reported
    frame count raises VideoSourceError after its last readable frame. name: the file path or "camera N".
    fps: frames per second the source reports (None for an image or a camera that does not say).
    size: (width, height) pixels. frame_count (also len()): the number of frames the container
    reports (an estimate for some formats, which may end early), 1 for an image, None for a camera.
    Use as a context manager, or call close(), to release the file or camera.
    """

    def __init__(self, name: str, capture: cv2.VideoCapture | None, first: Frame,
                 fps: float | None, frame_count: int | None):
        self.name, self.fps, self.frame_count = name, fps, frame_count
        self.size = (first.image.shape[1], first.image.shape[0])
        self._capture, self._first, self._started = capture, first, False
        self._clock_start = time.monotonic()
        if capture is not None:
            self._finalizer = weakref.finalize(self, capture.release)

    def __iter__(self) -> Iterator[Frame]:
        if self._started:
            raise RuntimeError(f"{self.name}: frames can be read only once; open the source again")
        self._started = True
        frame = self._first
        while frame is not None:
            yield frame
            read, frame = frame.index + 1, self._read(frame.index + 1, frame.timestamp)
        if self.frame_count and read < self.frame_count - max(2, 0.02 * self.frame_count):
            raise VideoSourceError(self.name, f"ended after {read} of its {self.frame_count} frames "
                                   "(truncated or corrupt); the frames before were read")

    def _read(self, index: int, previous_time: float) -> Frame | None:
        """The next frame from the capture, or None at the end (or for a still image)."""
        if self._capture is None or not self._capture.isOpened():
            return None
        with quiet_native_logs():
            ok, bgr = self._capture.read()
        if not ok:
            return None
        return Frame(index, self._timestamp(previous_time), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))

    @property
    def live(self) -> bool:
        """True for a camera (no length, timestamps from the clock)."""
        return self.frame_count is None

    def _timestamp(self, previous_time: float) -> float:
        """Seconds of the frame just read: the camera's clock or the file's presentation time.

        A file whose times do not increase (missing or broken timestamps) gets previous + 1 / fps
        (1 / 30 s when the file has no frame rate either).
        """
        if self.live:
            return time.monotonic() - self._clock_start
        seconds = self._capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if not seconds > previous_time:
            seconds = previous_time + 1.0 / (self.fps or 30.0)
        return seconds

    def __len__(self) -> int:
        if self.live:
            raise TypeError(f"{self.name}: a live camera has no length")
        return self.frame_count

    def close(self) -> None:
        """Release the file or camera; iteration stops."""
        if self._capture is not None:
            self._finalizer()

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_frames(source: str | Path | int) -> FrameSource:
    """Open a video file, a still image (see IMAGE_SUFFIXES) or a camera (its index, e.g. 0).

    The first frame is read at once, so a source that gives no frame fails here. Raises
    VideoSourceError naming the source for a missing, empty, unreadable or corrupt file, a video
    without frames, an image format OpenCV cannot read, or a camera that does not open.
    """
    if isinstance(source, int):
        return _open_camera(source)
    path = Path(source)
    if not path.is_file():
        raise VideoSourceError(path, "file not found" if not path.exists() else "not a file")
    if path.stat().st_size == 0:
        raise VideoSourceError(path, "file is empty")
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return _open_image(path)
    kind = mimetypes.guess_type(path.name)[0] or ""
    if kind.startswith("image/") and kind != "image/gif":
        raise VideoSourceError(
            path, f"unsupported image format {suffix!r}; readable images: {', '.join(IMAGE_SUFFIXES)}"
        )
    return _open_video(path)


def _open_image(path: Path) -> FrameSource:
    with quiet_native_logs():
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)  # 3 channels: drops alpha, expands grey; EXIF-rotated
    if bgr is None:
        raise VideoSourceError(
            path, f"cannot decode the image (corrupt, or a {path.suffix} variant OpenCV cannot read)"
        )
    return FrameSource(str(path), None, Frame(0, 0.0, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)), None, 1)


def _open_video(path: Path) -> FrameSource:
    with quiet_native_logs():
        capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not capture.isOpened():
        raise VideoSourceError(path, "cannot decode as a video (corrupt, truncated, or not a video format)")
    fps = capture.get(cv2.CAP_PROP_FPS)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    with quiet_native_logs():
        ok, bgr = capture.read()
    if not ok:
        capture.release()
        raise VideoSourceError(path, "the video has no frames that can be decoded")
    first = Frame(0, capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return FrameSource(str(path), capture, first, fps if fps > 0 else None, max(count, 1))


def _open_camera(index: int) -> FrameSource:
    name = f"camera {index}"
    with quiet_native_logs():
        capture = cv2.VideoCapture(index)
        ok, bgr = capture.read() if capture.isOpened() else (False, None)
    if not ok:
        capture.release()
        raise VideoSourceError(name, "cannot open the camera or read a frame from it (is it connected, and free?)")
    fps = capture.get(cv2.CAP_PROP_FPS)
    return FrameSource(name, capture, Frame(0, 0.0, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)),
                       fps if fps > 0 else None, None)


class VideoWriter:
    """Writes RGB frames to a video file with PyAV (FFmpeg); the frame size is fixed by the first frame.

    path: the output file (its folder is created); .mp4 by default. fps: frames per second.
    codec: an FFmpeg encoder, "libx264" (H.264, yuv420p: plays in browsers, QuickTime, Blender) by
    default; "mpeg4" or "mjpeg" (.avi) also work. H.264 needs even sides: an odd-sized frame gets its
    last row or column repeated. Use as a context manager: the file is finalised (readable, with
    every frame written so far) when the block ends, also when it ends with an exception. close()
    does the same; so does garbage collection of a writer never closed. No file is made when no
    frame was written.
    """

    def __init__(self, path: str | Path, fps: float, codec: str = "libx264"):
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        if codec not in av.codecs_available:
            raise ValueError(f"codec must be an FFmpeg encoder such as 'libx264', 'mpeg4' or 'mjpeg', got {codec!r}")
        self.path, self.fps, self.codec = Path(path), float(fps), codec
        self.frames_written = 0
        self._stream = None
        self._size: tuple[int, int] | None = None
        self._closed = False

    def write(self, image: np.ndarray) -> None:
        """Append one frame: image (H, W, 3) uint8 RGB, the same size as the first frame."""
        if self._closed:
            raise RuntimeError(f"{self.path}: the video writer is closed")
        image = check_image(image)
        size = (image.shape[1], image.shape[0])
        if self._stream is None:
            self._open(size)
        elif size != self._size:
            raise ValueError(f"{self.path}: frame is {size[0]}x{size[1]}, the video is {self._size[0]}x{self._size[1]}")
        padded = np.pad(image, ((0, size[1] % 2), (0, size[0] % 2), (0, 0)), mode="edge")
        for packet in self._stream.encode(av.VideoFrame.from_ndarray(padded, format="rgb24")):
            self._container.mux(packet)
        self.frames_written += 1

    def _open(self, size: tuple[int, int]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            container = av.open(str(self.path), "w")
            stream = container.add_stream(self.codec, rate=Fraction(self.fps).limit_denominator(1001))
        except (av.FFmpegError, ValueError) as error:
            raise VideoSourceError(self.path, f"cannot write a {self.codec!r} video here ({error})") from None
        stream.width, stream.height = size[0] + size[0] % 2, size[1] + size[1] % 2
        stream.pix_fmt = "yuvj420p" if self.codec == "mjpeg" else "yuv420p"
        if self.codec == "libx264":
            stream.options = {"preset": "ultrafast", "crf": "23"}   # about 4 ms a 640x480 frame
        self._container, self._stream, self._size = container, stream, size
        self._finalizer = weakref.finalize(self, _finish, container, stream)

    def close(self) -> None:
        """Finalise the file; further writes fail."""
        self._closed = True
        if self._stream is not None:
            self._finalizer()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _finish(container, stream) -> None:
    """Flush the encoder's buffered frames into the file and close it."""
    for packet in stream.encode():
        container.mux(packet)
    container.close()
