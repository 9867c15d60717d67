"""A browser view of people captured live (humotion capture --live): each person's skeleton in
3D, coloured as in the overlay video, and the newest camera frame with its 2D overlay in the
side panel. Built on viser like humotion.viewer.app; updates are sent as they come, the camera
frame at most `image_hz` times a second to spare the socket.

    view = LiveView()                               # prints nothing; view.url is the address
    view.show({0: joints}, overlay_image)           # joints (22, 3) metres, Y up
"""

from __future__ import annotations

import contextlib
import io
import time

import numpy as np
import torch

from humotion.canonical import PARENTS
from humotion.capture.overlay import person_color

_BONES = [(parent, joint) for joint, parent in enumerate(PARENTS) if parent >= 0]


class LiveView:
    """Serve live skeletons in a browser until stop(); host/port as for MotionViewer (port 0:
    any free port). image_width: pixels of the camera frame shown in the panel."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, image_width: int = 360, image_hz: float = 10.0):
        import viser

        with contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=host, port=port, label="humotion live", verbose=False)
        self.server.scene.set_up_direction("+y")
        self.server.scene.add_grid("/ground", width=10.0, height=10.0, plane="xz", cell_size=0.5, position=(0.0, 0.0, -4.0))
        self.server.initial_camera.position = (0.0, 1.6, 1.5)     # just behind the real camera
        self.server.initial_camera.look_at = (0.0, 1.0, -4.0)
        self.image_width, self._image_period = image_width, 1.0 / image_hz
        self._image = None
        self._image_sent = 0.0
        self._people: dict[int, object] = {}

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    @property
    def shown(self) -> set[int]:
        """Ids of the people visible now."""
        return {i for i, handle in self._people.items() if handle.visible}

    def show(self, people: dict[int, torch.Tensor], image: np.ndarray | None = None) -> None:
        """Show this frame: people {id: (22, 3) joints, metres, Y up}; image (H, W, 3) uint8 RGB."""
        with self.server.atomic():
            for person_id, joints in people.items():
                segments = np.asarray(joints, dtype=np.float32)[np.array(_BONES)]       # (21, 2, 3)
                handle = self._people.get(person_id)
                if handle is None:
                    self._people[person_id] = self.server.scene.add_line_segments(
                        f"/people/{person_id}", segments, person_color(person_id), thickness=0.03)
                else:
                    handle.points, handle.visible = segments, True
            for person_id, handle in self._people.items():
                if person_id not in people:
                    handle.visible = False
        if image is not None and time.monotonic() - self._image_sent >= self._image_period:
            self._show_image(image)

    def _show_image(self, image: np.ndarray) -> None:
        import cv2

        height = round(image.shape[0] * self.image_width / image.shape[1])
        small = cv2.resize(image, (self.image_width, height), interpolation=cv2.INTER_AREA)
        if self._image is None:
            self._image = self.server.gui.add_image(small, label="camera", format="jpeg", jpeg_quality=70)
        else:
            self._image.image = small
        self._image_sent = time.monotonic()

    def stop(self) -> None:
        self.server.stop()
