"""The messages of ``humotion serve`` (docs/live.md has the full description and examples).

A client opens a WebSocket, optionally sends a hello (JSON), then one headset frame per
message, as JSON text or as BINARY (the compact form below); the server answers each frame with
one body pose in the same form. Control messages (hello, calibrate, reset) and the server's
welcome, skeleton and error messages are always JSON text.

Binary frame, client -> server, FRAME.size = 96 bytes, little-endian::

    offset  type        field
    0       uint8       version (1)
    1       uint8       kind (1: headset frame)
    2       uint8       flags: bit 0 left hand visible, bit 1 right hand visible
    3       uint8       reserved (0)
    4       float64     timestamp, seconds
    12      float32[7]  head: px py pz qw qx qy qz (metres; unit quaternion, scalar first)
    40      float32[7]  left wrist, the same (ignored when not visible)
    68      float32[7]  right wrist, the same

Binary pose, server -> client, POSE.size = 640 bytes, little-endian::

    0       uint8       version (1)
    1       uint8       kind (2: body pose)
    2       uint8       flags (0)
    3       uint8       reserved (0)
    4       float64     timestamp of the frame this pose answers, seconds
    12      float32[3]  root (pelvis) world position, metres
    24      float32[88] 22 joints' local rotations, qw qx qy qz each (joint 0: global)
    376     float32[66] 22 joints' world positions, x y z each, metres

Joints are humotion.canonical.JOINTS in order. Every pose and position is in the connection's
convention (humotion.sparse.recording: openxr, unity, humotion), both ways: a local rotation R
is sent as C R C^T and a position p as C p, with C the convention's axes matrix, so the rest pose
(every rotation the identity) is a T-pose facing the convention's forward.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field

import numpy as np

from humotion.canonical import JOINTS
from humotion.sparse.recording import CONVENTIONS, HAND_FRAMES, HeadsetFrame, hand_offset

VERSION = 1
FRAME_KIND, POSE_KIND = 1, 2
FRAME = struct.Struct("<BBBBd21f")
POSE = struct.Struct(f"<BBBBd{3 + 22 * 4 + 22 * 3}f")
LEFT_VISIBLE, RIGHT_VISIBLE = 1, 2


class ProtocolError(ValueError):
    """A message the server cannot use; its text is sent back to the client."""


@dataclass
class Hello:
    """A connection's settings: from the query string, then the hello message.

    convention: axes of every pose both ways (CONVENTIONS). hand_frame: what a hand's identity
    orientation means (HAND_FRAMES). height: the user's standing height in metres (None: from
    the first frame's eye height). token: the shared secret, when the server has one.
    """

    convention: str = "openxr"
    hand_frame: str = "tpose"
    height: float | None = None
    token: str | None = None

    def updated(self, fields: dict, source: str) -> "Hello":
        known = {"convention", "hand_frame", "height", "token"}
        out = Hello(self.convention, self.hand_frame, self.height, self.token)
        for key, value in fields.items():
            if key in ("type", "version"):
                continue
            if key not in known:
                raise ProtocolError(f"{source}: unknown field {key!r}; expected {', '.join(sorted(known))}")
            setattr(out, key, value)
        if out.convention not in CONVENTIONS:
            raise ProtocolError(f"{source}: convention {out.convention!r}; expected one of {', '.join(CONVENTIONS)}")
        if out.hand_frame not in HAND_FRAMES:
            raise ProtocolError(f"{source}: hand_frame {out.hand_frame!r}; expected one of {', '.join(HAND_FRAMES)}")
        if out.height is not None:
            try:
                out.height = float(out.height)
            except (TypeError, ValueError):
                raise ProtocolError(f"{source}: height {out.height!r} is not a number of metres") from None
            if not 0.5 <= out.height <= 2.5:
                raise ProtocolError(f"{source}: height {out.height} m is outside 0.5-2.5 m")
        if out.token is not None and not isinstance(out.token, str):
            raise ProtocolError(f"{source}: token must be a string")
        return out


def hello_from_query(query: str) -> Hello:
    """The settings in a connection URL's query string (?convention=unity&height=1.8&token=...)."""
    from urllib.parse import parse_qsl

    try:
        pairs = parse_qsl(query, strict_parsing=bool(query), max_num_fields=8)
    except ValueError as error:
        raise ProtocolError(f"query string: {error}") from None
    return Hello().updated(dict(pairs), "query string")


@dataclass
class Axes:
    """A connection's change of axes (module docstring) between its convention and humotion's."""

    convention: str = "openxr"
    hand_frame: str = "tpose"
    c: np.ndarray = field(init=False)
    quat: np.ndarray = field(init=False)        # (w, x, y, z) multipliers: q -> q of C R C^T
    hands: tuple = field(init=False)

    def __post_init__(self):
        self.c = np.diag(CONVENTIONS[self.convention]).astype(np.float64)
        det = float(np.prod(self.c))
        self.quat = np.concatenate([[1.0], det * self.c])
        self.hands = tuple(hand_offset(side, self.hand_frame).numpy() for side in ("left", "right"))

    def device(self, values, hand: int | None) -> tuple:
        """(px, py, pz, qw, qx, qy, qz) in the convention -> (rotation (3, 3), position (3,)) in
        humotion's axes; hand 0 / 1 adds the hand frame's offset."""
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (7,) or not np.isfinite(v).all():
            raise ValueError("needs 7 finite numbers: px py pz qw qx qy qz")
        norm = float(np.linalg.norm(v[3:]))
        if not 0.5 < norm < 2.0:
            raise ValueError(f"quaternion has length {norm:.3g}, not a unit quaternion")
        r = quat_to_matrix(v[3:] * self.quat / norm)
        if hand is not None:
            r = r @ self.hands[hand]
        return r, v[:3] * self.c

    def pose(self, rotations, root, positions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A TrackedPose's (22, 4) local wxyz rotations, (3,) root, (22, 3) positions -> the convention."""
        return (np.asarray(rotations, dtype=np.float64) * self.quat, np.asarray(root, dtype=np.float64) * self.c,
                np.asarray(positions, dtype=np.float64) * self.c)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """A unit quaternion (w, x, y, z) -> its (3, 3) rotation matrix."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def read_message(message: str | bytes) -> dict | bytes:
    """A text message -> its JSON object (ProtocolError when it is not one); bytes pass through."""
    if isinstance(message, bytes):
        return message
    try:
        value = json.loads(message)
    except ValueError as error:
        raise ProtocolError(f"not JSON: {error}") from None
    if not isinstance(value, dict) or not isinstance(value.get("type", "frame"), str):
        raise ProtocolError('a JSON message is an object with a "type" (hello, frame, calibrate, reset)')
    return value


def frame_from_binary(data: bytes, axes: Axes) -> HeadsetFrame:
    """A binary frame (module docstring) -> HeadsetFrame; ProtocolError naming the problem."""
    if len(data) != FRAME.size:
        raise ProtocolError(f"binary frame of {len(data)} bytes; expected {FRAME.size} (version {VERSION})")
    version, kind, flags, _, t, *values = FRAME.unpack(data)
    if version != VERSION or kind != FRAME_KIND:
        raise ProtocolError(f"binary frame version {version} kind {kind}; expected version {VERSION} kind {FRAME_KIND}")
    return _frame(t, values[0:7], values[7:14] if flags & LEFT_VISIBLE else None,
                  values[14:21] if flags & RIGHT_VISIBLE else None, axes)


def frame_from_json(message: dict, axes: Axes) -> HeadsetFrame:
    """{"type": "frame", "t": s, "head": [7], "left": [7] | null, "right": [7] | null} -> HeadsetFrame
    (a hand is visible when it holds a pose; "left_visible": false hides it anyway)."""
    unknown = set(message) - {"type", "t", "head", "left", "right", "left_visible", "right_visible"}
    if unknown:
        raise ProtocolError(f"frame: unknown field {sorted(unknown)[0]!r}")
    if "t" not in message or "head" not in message:
        raise ProtocolError('frame: needs "t" (seconds) and "head" ([px, py, pz, qw, qx, qy, qz])')
    hands = [None if not message.get(f"{side}_visible", True) else message.get(side) for side in ("left", "right")]
    return _frame(message["t"], message["head"], *hands, axes)


def _frame(t, head, left, right, axes: Axes) -> HeadsetFrame:
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
        raise ProtocolError(f"frame: t must be a finite number of seconds, got {t!r}")
    devices = []
    for name, values, hand in (("head", head, None), ("left", left, 0), ("right", right, 1)):
        if values is None and name != "head":
            devices.append(None)
            continue
        try:
            devices.append(axes.device(values, hand))
        except (ValueError, TypeError) as error:
            raise ProtocolError(f"frame: {name} {error}") from None
    return HeadsetFrame(float(t), *devices)


def pose_binary(t: float, rotations, root, positions, axes: Axes) -> bytes:
    """A body pose (humotion's axes) as the binary pose message, in the connection's convention."""
    q, r, p = axes.pose(rotations, root, positions)
    return POSE.pack(VERSION, POSE_KIND, 0, 0, t, *r.tolist(), *q.ravel().tolist(), *p.ravel().tolist())


def pose_json(t: float, rotations, root, positions, axes: Axes) -> str:
    """A body pose as `{"type": "pose", "t", "root" [3], "rotations" [22][4] wxyz, "positions" [22][3]}`."""
    q, r, p = axes.pose(rotations, root, positions)
    return json.dumps({"type": "pose", "t": t, "root": np.round(r, 6).tolist(),
                       "rotations": np.round(q, 6).tolist(), "positions": np.round(p, 6).tolist()})


def read_pose_binary(data: bytes) -> dict:
    """A binary pose -> {"t", "root" (3,), "rotations" (22, 4), "positions" (22, 3)} (clients, tests)."""
    if len(data) != POSE.size:
        raise ProtocolError(f"binary pose of {len(data)} bytes; expected {POSE.size}")
    version, kind, _, _, t, *values = POSE.unpack(data)
    v = np.asarray(values, dtype=np.float32)
    return {"t": t, "root": v[:3], "rotations": v[3:91].reshape(22, 4), "positions": v[91:].reshape(22, 3)}


def frame_binary(t: float, head, left=None, right=None) -> bytes:
    """A binary frame from (7,) devices in the connection's convention (None: hand not visible)."""
    flags = (LEFT_VISIBLE if left is not None else 0) | (RIGHT_VISIBLE if right is not None else 0)
    zeros = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    return FRAME.pack(VERSION, FRAME_KIND, flags, 0, t, *head, *(left if left is not None else zeros),
                      *(right if right is not None else zeros))


def skeleton_json(skeleton, axes: Axes) -> str:
    """The tracked body's rest skeleton: `{"type": "skeleton", "height", "joints", "parents", "offsets" [22][3]}`."""
    return json.dumps({"type": "skeleton", "height": round(float(skeleton.height()), 4), "joints": list(JOINTS),
                       "parents": list(skeleton.parents),
                       "offsets": np.round(np.asarray(skeleton.offsets) * axes.c, 6).tolist()})


def stream_frames(stream, convention: str = "openxr", hand_frame: str = "tpose") -> list[tuple]:
    """A HeadsetStream (humotion.sparse.recording) as the frames a client sends: per frame
    (t, head, left, right), each device 7 numbers (px py pz qw qx qy qz) in the convention, a
    hand None when not visible. For replaying recordings (tests, bench/serve_load.py)."""
    import torch

    from humotion.sparse.recording import from_humotion

    devices = []
    for k, side, r, p in ((-1, "head", stream.head_rotations, stream.head_positions),
                          (0, "left", stream.left_rotations, stream.left_positions),
                          (1, "right", stream.right_rotations, stream.right_positions)):
        offset = torch.eye(3, dtype=torch.float64) if k < 0 else hand_offset(side, hand_frame)
        seen = torch.ones(len(stream), dtype=torch.bool) if k < 0 else stream.visible[:, k]
        known = seen & torch.isfinite(r).all(-1).all(-1) & torch.isfinite(p).all(-1)
        q, pf = from_humotion(torch.where(known[:, None, None], r, torch.eye(3, dtype=r.dtype)),
                              torch.where(known[:, None], p, 0.0), convention, offset)
        values = torch.cat([pf, q], dim=1).tolist()
        devices.append([v if ok else None for v, ok in zip(values, known.tolist())])
    return [(float(t), *d) for t, *d in zip(stream.timestamps.tolist(), *devices)]
