"""A body as VMC: the Virtual Motion Capture protocol (OSC over UDP) that VSeeFace, Warudo,
VNyan and Unity (EVMC4U) receive, usually on port 39539.

Per frame one sender writes (OSC bundles, each datagram at most MAX_DATAGRAM bytes):

- ``/VMC/Ext/OK (int)1 (int)3 (int)0 (int)1``: a model is loaded, calibrated, normal mode, tracking.
- ``/VMC/Ext/T (float)seconds``: the frame's time.
- ``/VMC/Ext/Root/Pos (string)"root" px py pz qx qy qz qw``: the avatar's root, kept at the
  origin with no turn; the body's place and facing are in the Hips bone.
- ``/VMC/Ext/Bone/Pos (string)BONE px py pz qx qy qz qw`` for each of the 22 bones of
  VMC_BONES: the local rotation (relative to the parent bone; Hips: to the root) and local
  position (Hips: the pelvis's world position; other bones: the skeleton's rest offset).

Rotations are relative to a T-pose whose bones all have the identity rest rotation, which is what
VRM avatars are normalised to, so a receiver can apply them as they are.

Axes. humotion: right-handed, Y up, the body faces +Z, its left is +X. Unity (and VMC):
left-handed, Y up, +Z forward, X right, so the body's left is -X. The change is the mirror
M = diag(-1, 1, 1) applied on both sides, which keeps left joints left:

- positions: (x, y, z) -> (-x, y, z)
- rotations: R -> M R M. For a unit quaternion (w, x, y, z) the axis is a pseudovector, which a
  mirror maps to -M a = (ax, -ay, -az) with the same angle, so (w, x, y, z) -> (w, x, -y, -z);
  VMC writes it in Unity's order (x, y, z, w), giving (x, -y, -z, w). A turn of the body to its
  left by a (about +Y in humotion) is a turn by -a about Unity's Y, also to the body's left.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterable

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from humotion.canonical import JOINTS

DEFAULT_PORT = 39539
MAX_DATAGRAM = 1400     # below an Ethernet MTU's payload, so no datagram is fragmented on a LAN

# canonical joint -> Unity HumanBodyBones name
VMC_BONES: dict[str, str] = {
    "pelvis": "Hips", "spine1": "Spine", "spine2": "Chest", "spine3": "UpperChest", "neck": "Neck", "head": "Head",
    **{f"{side}_{joint}": f"{side.capitalize()}{bone}" for side in ("left", "right") for joint, bone in (
        ("hip", "UpperLeg"), ("knee", "LowerLeg"), ("ankle", "Foot"), ("foot", "Toes"), ("collar", "Shoulder"),
        ("shoulder", "UpperArm"), ("elbow", "LowerArm"), ("wrist", "Hand"))},
}
assert set(VMC_BONES) == set(JOINTS), "every canonical joint has a HumanBodyBones name"
BONE_NAMES: tuple[str, ...] = tuple(VMC_BONES[j] for j in JOINTS)   # in canonical joint order

_MIRROR = np.array([-1.0, 1.0, 1.0])


def unity_positions(positions: np.ndarray) -> np.ndarray:
    """(..., 3) humotion positions (metres) -> Unity's axes: x negated."""
    return np.asarray(positions, dtype=np.float64) * _MIRROR


def unity_quaternions(quaternions_wxyz: np.ndarray) -> np.ndarray:
    """(..., 4) humotion rotations, unit quaternions (w, x, y, z) -> the same rotations mirrored
    into Unity's axes, in Unity's order (x, y, z, w): (x, -y, -z, w)."""
    q = np.asarray(quaternions_wxyz, dtype=np.float64)
    return np.stack([q[..., 1], -q[..., 2], -q[..., 3], q[..., 0]], axis=-1)


def parse_address(text: str, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """'HOST:PORT' (or 'HOST', or ':PORT' for 127.0.0.1) -> (host, port); ValueError naming the problem."""
    host, sep, port = str(text).rpartition(":")
    if not sep:
        host, port = port, str(default_port)
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"VMC address {text!r}: the port must be a number from 1 to 65535 (HOST:PORT, e.g. 127.0.0.1:39539)")
    return host, int(port)


def _message(address: str, *values) -> OscMessage:
    builder = OscMessageBuilder(address)
    for value in values:
        builder.add_arg(value)
    return builder.build()


def frame_messages(rotations: np.ndarray, root_position: np.ndarray, offsets: np.ndarray, t: float) -> list[OscMessage]:
    """One body pose as VMC messages (module docstring), in sending order.

    Args:
        rotations (22, 4) wxyz: canonical local rotations, joint 0 global, humotion's axes.
        root_position (3,): the pelvis's world position, metres.
        offsets (22, 3): each joint's rest offset from its parent, metres (Skeleton.offsets).
        t: the frame's time in seconds.
    """
    q = unity_quaternions(rotations)
    p = unity_positions(offsets).copy()
    p[0] = unity_positions(root_position)
    messages = [_message("/VMC/Ext/OK", 1, 3, 0, 1), _message("/VMC/Ext/T", float(t)),
                _message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)]
    for name, pj, qj in zip(BONE_NAMES, p.tolist(), q.tolist()):
        messages.append(_message("/VMC/Ext/Bone/Pos", name, *pj, *qj))
    return messages


def bundles(messages: Iterable[OscMessage], limit: int = MAX_DATAGRAM) -> list[bytes]:
    """Messages packed in order into OSC bundles of at most ``limit`` bytes each."""
    out, builder, size = [], None, 0
    for message in messages:
        need = 4 + message.size
        if builder is not None and size + need > limit:
            out.append(builder.build().dgram)
            builder = None
        if builder is None:
            builder, size = OscBundleBuilder(IMMEDIATELY), 16      # "#bundle\0" + time tag
        builder.add_content(message)
        size += need
    if builder is not None:
        out.append(builder.build().dgram)
    return out


class VmcSender:
    """Sends body poses as VMC to one receiver (UDP: nothing waits for or hears back from it).

    address: (host, port). offsets (22x3): the body's rest offsets (Skeleton.offsets), metres.
    """

    def __init__(self, address: tuple[str, int], offsets: np.ndarray | None = None):
        self.offsets = None if offsets is None else np.asarray(offsets, dtype=np.float64)
        try:
            family, _, _, _, self.address = socket.getaddrinfo(*address, type=socket.SOCK_DGRAM)[0]
        except OSError as error:
            raise ValueError(f"VMC address {address[0]}:{address[1]}: {error.strerror or error}") from None
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.sent = self.dropped = 0

    def send(self, rotations, root_position, t: float, offsets: np.ndarray | None = None) -> None:
        """One pose (see frame_messages): rotations (22, 4) wxyz, root_position (3,) metres, t
        seconds, offsets (22, 3) metres (default the sender's); a datagram the system cannot take
        now is dropped and counted (``dropped``), never waited for."""
        offsets = self.offsets if offsets is None else offsets
        if offsets is None:
            raise ValueError("VmcSender.send: no rest offsets: pass offsets (the skeleton's) here or to the sender")
        for datagram in bundles(frame_messages(np.asarray(rotations), np.asarray(root_position), offsets, t)):
            try:
                self._socket.sendto(datagram, self.address)
                self.sent += 1
            except (BlockingIOError, ConnectionRefusedError):
                self.dropped += 1

    def close(self) -> None:
        self._socket.close()

    def __enter__(self) -> "VmcSender":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def stream_motion(motion, sender: VmcSender, rate: float | None = None, clock: Callable[[], float] = time.monotonic,
                  sleep: Callable[[float], None] = time.sleep) -> int:
    """Send a Motion (canonical skeleton) frame by frame in real time at ``rate`` frames per
    second (None: the motion's own; math.inf: as fast as possible); returns the frames sent.
    Frames are paced against the clock, so a slow send does not stretch the stream."""
    rate = motion.fps if rate is None else rate
    if not rate > 0:
        raise ValueError(f"VMC rate must be positive, got {rate}")
    if tuple(motion.skeleton.names) != JOINTS:
        raise ValueError("VMC output needs a body on humotion's canonical skeleton (22 joints)")
    rotations = motion.rotations.detach().cpu().numpy().astype(np.float64)
    roots = motion.root_positions.detach().cpu().numpy().astype(np.float64)
    offsets = np.asarray(motion.skeleton.offsets, dtype=np.float64)
    start = clock()
    for i in range(len(rotations)):
        if math.isfinite(rate):
            wait = start + i / rate - clock()
            if wait > 0:
                sleep(wait)
        sender.send(rotations[i], roots[i], i / motion.fps, offsets)
    return len(rotations)
