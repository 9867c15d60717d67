"""BVH (Biovision Hierarchy) motion files: read one into a Motion, write a Motion as one.

Why a parser of our own: the BVH packages on PyPI build a Python object per joint and convert the
motion block value by value (seconds for a long take), report malformed input with bare
IndexError/ValueError and no line number, do not read gzip, and fix conventions we need to
control: per-joint channel orders, position channels on non-root joints, length units. Here the
small hierarchy is read line by line and the motion block a few megabytes at a time, each block
with one numpy conversion, into arrays allocated once from the Frames: count.

Reading conventions
- Rotation channels: any order and any subset of X/Y/Z per joint, in degrees. A list
  "Zrotation Yrotation Xrotation" is the intrinsic rotation R = Rz @ Ry @ Rx (roma convention
  "ZYX"); missing axes are zero, a joint without channels keeps the identity.
- Root position channels are added to the root OFFSET: world root = OFFSET + channels. Most files
  (CMU cgspeed, salsa, and what write_bvh writes) have a zero root OFFSET, where this agrees with
  readers that let the channels replace the OFFSET (Blender's importer does). iClone/Character
  Creator exports put the rest hip height in the OFFSET (105 cm) and ~7 cm in the channels; only
  adding them puts those characters' feet on the floor (replacing leaves the hips 7 cm up).
- Position channels on a non-root joint replace that joint's OFFSET on each frame (the reading of
  MotionBuilder and Blender, whose exporters write the offset itself into such channels). Such
  files give Motion.joint_offsets (T, J, 3); when only the root has position channels it is None.
- End Site blocks become skeleton end sites named f"{parent}_end" (then "_end2", ... if several).
- Frame rate: fps = 1 / Frame Time, snapped to the integer n when 1/n, written with as many
  decimals as the file used, is the file's Frame Time and n * Frame Time is within 0.1% of 1
  (0.008333 and .0083333 -> 120, 0.016667 -> 60; 0.033367 stays 29.97 and 0.012 stays 83.33).
  Exporters write a rounded 1/n; snapping undoes that rounding and nothing coarser.
- Units: BVH has no unit field. units="auto" chooses, among UNITS (metres per file unit), the one
  that makes the figure's size closest to 1.7 m in log ratio. The size is the largest extent, over
  the three axes and over up to 64 evenly spaced frames, of the posed joints and end sites (posed,
  because a rest pose need not be upright: the iClone rig's zero pose points every bone along its
  local +Y; several frames, because a take may start crouched). The decision boundaries lie
  halfway, in log ratio, between neighbouring units (inch/cmu are 2.2x apart, cm/inch 2.54x), so
  every unit is found for figures whose size is between 1.14 m and 2.53 m; outside that range
  (a doll, a giant) pass units= yourself. A figure of zero size reads as metres. On the project
  data: CMU cgspeed -> 'cmu' (1.58 m), iClone -> 'cm' (1.54-2.24 m), salsa -> 'm' (1.24-1.44 m).
- Style: the file's units (as chosen) and each joint's rotation order are remembered with the
  skeleton read (BvhStyle); write_bvh writes a motion on that skeleton the same way.
- Limits: a rotation channel beyond MAX_ANGLE (1e6 degrees), an OFFSET or position channel beyond
  MAX_LENGTH (1e9 file units), NaN or infinity are refused with the file's line, the frame, the
  joint and the channel.
"""

from __future__ import annotations

import gzip
import io
import os
import re
import weakref
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, file_stem
from humotion.io.paths import write_atomic
from humotion.motion import Motion
from humotion.skeleton import Skeleton, forward_kinematics

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254, "cmu": 0.0254 / 0.45}
"""Metres per file unit for each name units= accepts. 'cmu': CMU's ASF unit, 1/0.45 inch."""

TYPICAL_FIGURE_SIZE = 1.7  # metres; what units="auto" aims at

MAX_ANGLE = 1e6
"""Largest magnitude of a rotation channel read, degrees. Takes hold angles within a few turns
(unwrapped ones within thousands); a larger value is corrupt data, whose rotation would be
rounding noise (1e30 degrees has no fraction of a turn left in float64)."""

MAX_LENGTH = 1e9
"""Largest magnitude of an OFFSET or position channel read, in file units (1000 km in mm)."""

_BLOCK_CHARS = 1 << 20  # motion rows are converted about this many characters at a time
_MAX_INDENT = 32  # write_bvh indents at most this many tabs: a deep chain stays linear in size
_WRITE_ROWS = 1024  # write_bvh formats and writes this many motion rows at a time
_FIGURE_FRAMES = 64  # frames units="auto" looks at

_CHANNEL_NAMES = {f"{axis}{kind}": (kind, "XYZ".index(axis.upper()))
                  for axis in "xyz" for kind in ("position", "rotation")}


@dataclass(eq=False)
class _Block:
    """A ROOT/JOINT or End Site as read from the hierarchy (lengths in file units)."""

    kind: str  # "joint" or "end"
    name: str
    parent: int
    line: int
    index: int = -1  # a joint's index in file order
    offset: list[float] | None = None
    channels: list[tuple[str, int]] = field(default_factory=list)  # (kind, axis) in file order
    has_channels: bool = False


class _Lines:
    """A BVH file's text, read on demand: header lines one at a time, motion rows in blocks.

    stream: the file as text (universal newlines; UTF-8 with undecodable bytes kept as
    surrogates, a header line holding them is read as Latin-1). number: 1-based number of the
    last line read; last: that of the last line read holding anything but whitespace (0: none).
    """

    def __init__(self, reader: "_Reader", stream: io.TextIOBase):
        self.reader, self.stream = reader, stream
        self.number = self.last = 0

    def line(self) -> str | None:
        """The next line without its newline, or None at the end of the file."""
        text = self.stream.readline()
        if not text:
            if not self.last:
                raise self.reader.fail("file is empty", None)
            return None
        self.number += 1
        self._check_text(text)
        text = text.rstrip("\n")
        if self.number == 1:
            text = text.lstrip("\ufeff")
        if not text.isascii():
            try:
                text.encode("utf-8")
            except UnicodeEncodeError:
                text = text.encode("utf-8", "surrogateescape").decode("latin-1")
        if text.strip():
            self.last = self.number
        return text

    def block(self) -> list[str]:
        """The next whole lines (about _BLOCK_CHARS characters) without newlines; [] at the end."""
        text = self.stream.read(_BLOCK_CHARS)
        if text and not text.endswith("\n"):
            text += self.stream.readline()
        self._check_text(text)
        lines = text.split("\n")
        if lines[-1] == "":
            lines.pop()
        self.number += len(lines)
        return lines

    def _check_text(self, text: str) -> None:
        if "\x00" in text:
            raise self.reader.fail("file is binary, not a text motion file", None)


@dataclass(eq=False)
class _Layout:
    """Where each joint's channels sit in a motion row of `count` values.

    offsets: (J, 3) rest offsets, file units. groups: per rotation order (e.g. "ZYX"), its joints
    and their columns (k, len(order)). root: (axis, column) of the root's position channels;
    moved: (joint, axis, column) of other joints' position channels. limits: (C,) the largest
    magnitude each column may hold (MAX_ANGLE or MAX_LENGTH); labels: (C,) (joint name, channel).
    """

    offsets: np.ndarray
    groups: list[tuple[str, list[int], list[list[int]]]]
    root: list[tuple[int, int]]
    moved: list[tuple[int, int, int]]
    limits: np.ndarray
    labels: list[tuple[str, str]]

    @classmethod
    def of(cls, joints: list[_Block]) -> "_Layout":
        groups: dict[str, tuple[list[int], list[list[int]]]] = {}
        root, moved, limits, labels = [], [], [], []
        for j, joint in enumerate(joints):
            order, rotation_columns = "", []
            for kind, axis in joint.channels:
                column = len(labels)
                labels.append((joint.name, f"{'XYZ'[axis]}{kind}"))
                limits.append(MAX_ANGLE if kind == "rotation" else MAX_LENGTH)
                if kind == "rotation":
                    order += "XYZ"[axis]
                    rotation_columns.append(column)
                elif j == 0:
                    root.append((axis, column))
                else:
                    moved.append((j, axis, column))
            if order:
                members, columns = groups.setdefault(order, ([], []))
                members.append(j)
                columns.append(rotation_columns)
        offsets = np.array([j.offset for j in joints], dtype=np.float64)
        return cls(offsets, [(order, *g) for order, g in groups.items()], root, moved,
                   np.array(limits, dtype=np.float64), labels)

    @property
    def count(self) -> int:
        """C, the number of values in a motion row."""
        return len(self.labels)

    def pose(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Local rotations (n, J, 4) float64 wxyz, root positions (n, 3) and joint offsets
        (n, J, 3) or None (file units, float64) from n motion rows (n, C) float64, degrees and
        file units."""
        n, joints = len(values), len(self.offsets)
        root = np.tile(self.offsets[0], (n, 1))
        for axis, column in self.root:
            root[:, axis] += values[:, column]
        joint_offsets = None
        if self.moved:
            joint_offsets = np.tile(self.offsets, (n, 1, 1))
            for j, axis, column in self.moved:
                joint_offsets[:, j, axis] = values[:, column]
        quats = np.zeros((n, joints, 4))
        quats[..., 0] = 1.0
        for order, members, columns in self.groups:
            quats[:, members] = _euler_to_quat(order, values[:, columns])  # (n, k, len(order)) degrees
        return quats, root, joint_offsets

    def problem(self, value: float, frame: int, column: int) -> str:
        """What is wrong with a value beyond its column's limit (or not finite)."""
        joint, channel = self.labels[column]
        where = f"frame {frame}, joint {joint!r}, channel {channel}"
        if not np.isfinite(value):
            return f"motion row holds NaN or infinity ({where})"
        unit = "degrees" if channel.endswith("rotation") else "file units"
        return f"motion value {value:g} is beyond ±{self.limits[column]:g} {unit} ({where})"


class _Poses:
    """A take's frames as its rows are read, in arrays allocated once for the frames a file can
    hold (grown only when a gzip file's size hint fell short): quats (T, J, 4) float32,
    root (T, 3) float64 and joint_offsets (T, J, 3) float32 or None, lengths in file units."""

    def __init__(self, layout: _Layout, frames: int, capacity: int):
        self.layout, self.frames = layout, frames
        self.quats, self.root, self.joint_offsets = self._rest(capacity)

    def _rest(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        offsets = self.layout.offsets
        moved = np.tile(offsets.astype(np.float32), (n, 1, 1)) if self.layout.moved else None
        quats = np.zeros((n, len(offsets), 4), dtype=np.float32)
        quats[..., 0] = 1.0
        return quats, np.tile(offsets[0], (n, 1)), moved

    def add(self, start: int, values: np.ndarray) -> None:
        """Frames start.. from their rows (n, C) float64."""
        end = start + len(values)
        if end > len(self.root):
            more = self._rest(min(self.frames, max(end, 2 * len(self.root))) - len(self.root))
            self.quats = np.concatenate([self.quats, more[0]])
            self.root = np.concatenate([self.root, more[1]])
            if self.joint_offsets is not None:
                self.joint_offsets = np.concatenate([self.joint_offsets, more[2]])
        quats, root, joint_offsets = self.layout.pose(values)
        self.quats[start:end] = quats
        self.root[start:end] = root
        if joint_offsets is not None:
            self.joint_offsets[start:end] = joint_offsets


@dataclass(frozen=True)
class _Header:
    """A BVH file up to its first motion row: joints and end sites (file order), Frames:, fps."""

    joints: list[_Block]
    ends: list[_Block]
    frames: int
    fps: float


class _Reader:
    """Raises MotionFileError for one file; keeps the path out of every call."""

    def __init__(self, path):
        self.path = path

    def fail(self, problem: str, line: int | None) -> MotionFileError:
        return MotionFileError(self.path, problem, line=line)

    def number(self, token: str, line: int, what: str, limit: float | None = None) -> float:
        """A finite float token, within ±limit when given."""
        value = self.parse(token, line, what)
        if not np.isfinite(value):
            raise self.fail(f"{what}: {token!r} is not a finite number", line)
        if limit is not None and abs(value) > limit:
            raise self.fail(f"{what}: {token!r} is beyond ±{limit:g}", line)
        return value

    def parse(self, token: str, line: int, what: str) -> float:
        try:
            return float(token)
        except ValueError:
            raise self.fail(f"{what}: {token!r} is not a number", line) from None

    # -- hierarchy ------------------------------------------------------------------------
    def header(self, lines: _Lines) -> _Header:
        """The hierarchy, Frames: and Frame Time:, read up to the first motion row."""
        joints, ends = self.hierarchy(lines)
        value, line = self.header_value(lines, r"frames\s*:?\s*(\S+)", "Frames:")
        frames = self.frame_count(value, line)
        value, line = self.header_value(lines, r"frame\s*time\s*:?\s*(\S+)", "Frame Time:")
        return _Header(joints, ends, frames, self.fps(value, line))

    def hierarchy(self, lines: _Lines) -> tuple[list[_Block], list[_Block]]:
        """Joints (file order) and end sites, read up to the MOTION line."""
        joints: list[_Block] = []
        names: set[str] = set()
        ends: list[_Block] = []
        stack: list[_Block] = []  # open blocks
        pending: _Block | None = None  # waiting for its "{"
        started = False
        while (text := lines.line()) is not None:
            line = lines.number
            tokens = text.replace("{", " { ").replace("}", " } ").split()
            k = 0
            while k < len(tokens):
                token, word = tokens[k], tokens[k].upper()
                stop = k + 1
                while stop < len(tokens) and tokens[stop] not in ("{", "}"):
                    stop += 1
                args = tokens[k + 1:stop]
                if not started:
                    if word != "HIERARCHY" or args:
                        raise self.fail(f"a BVH file starts with HIERARCHY, found {text.strip()[:40]!r}", line)
                    started = True
                elif pending is not None and token != "{":
                    what = "End Site" if pending.kind == "end" else repr(pending.name)
                    raise self.fail(f"expected '{{' to open {what}, found {token!r}", line)
                elif token == "{":
                    if pending is None:
                        raise self.fail("'{' without ROOT, JOINT or End Site before it", line)
                    stack.append(pending)
                    pending, stop = None, k + 1
                elif token == "}":
                    if not stack:
                        raise self.fail("unbalanced braces: '}' without a matching '{'", line)
                    block = stack.pop()
                    if block.offset is None:
                        what = "End Site" if block.kind == "end" else f"joint {block.name!r}"
                        raise self.fail(f"{what} (line {block.line}) has no OFFSET", line)
                    stop = k + 1
                elif word in ("ROOT", "JOINT"):
                    if not args:
                        raise self.fail(f"{word} without a joint name", line)
                    name = "_".join(args)
                    if word == "ROOT" and (joints or stack):
                        raise self.fail("a second ROOT: only files with one skeleton are supported", line)
                    if word == "JOINT" and (not stack or stack[-1].kind != "joint"):
                        raise self.fail("JOINT outside a ROOT or JOINT block", line)
                    if name in names:
                        raise self.fail(f"duplicate joint name {name!r}", line)
                    parent = stack[-1].index if word == "JOINT" else -1
                    pending = _Block("joint", name, parent, line, index=len(joints))
                    joints.append(pending)
                    names.add(name)
                elif word == "END":
                    if not args or args[0].upper() != "SITE":
                        raise self.fail("expected 'End Site'", line)
                    if not stack or stack[-1].kind != "joint":
                        raise self.fail("End Site outside a ROOT or JOINT block", line)
                    pending = _Block("end", "", stack[-1].index, line)
                    ends.append(pending)
                elif word == "OFFSET":
                    if not stack:
                        raise self.fail("OFFSET outside a ROOT, JOINT or End Site block", line)
                    if stack[-1].offset is not None:
                        raise self.fail("a second OFFSET in one block", line)
                    if len(args) != 3:
                        raise self.fail(f"OFFSET needs 3 numbers, found {len(args)}", line)
                    stack[-1].offset = [self.number(a, line, "OFFSET", MAX_LENGTH) for a in args]
                elif word == "CHANNELS":
                    self.channels(stack, args, line)
                elif word == "MOTION":
                    if args or stop < len(tokens):
                        raise self.fail("unexpected text after MOTION", line)
                    if pending is not None or stack:
                        opened = (pending or stack[-1]).line
                        raise self.fail(f"unbalanced braces: MOTION reached with a block still open (opened at line {opened})", line)
                    if not joints:
                        raise self.fail("no ROOT joint before MOTION", line)
                    return joints, ends
                else:
                    raise self.fail(f"unknown keyword {token!r} in the hierarchy", line)
                k = stop
        if stack or pending is not None:
            raise self.fail("file ends inside the hierarchy (truncated?)", lines.last)
        raise self.fail("no MOTION section", lines.last)

    def channels(self, stack: list[_Block], args: list[str], line: int) -> None:
        if not stack or stack[-1].kind != "joint":
            raise self.fail("CHANNELS outside a ROOT or JOINT block", line)
        block = stack[-1]
        if block.has_channels:
            raise self.fail("a second CHANNELS in one joint", line)
        if not args or not (args[0].isascii() and args[0].isdigit()):
            raise self.fail("CHANNELS needs a count, then the channel names", line)
        count, names = int(args[0]), args[1:]
        if count != len(names):
            raise self.fail(f"CHANNELS says {count} but lists {len(names)} channel names", line)
        for name in names:
            channel = _CHANNEL_NAMES.get(name.lower())
            if channel is None:
                raise self.fail(f"unknown channel {name!r} (expected X/Y/Z position or rotation)", line)
            if channel in block.channels:
                raise self.fail(f"channel {name!r} listed twice", line)
            block.channels.append(channel)
        block.has_channels = True

    # -- motion ---------------------------------------------------------------------------
    def header_value(self, lines: _Lines, pattern: str, what: str) -> tuple[str, int]:
        """The value of the next non-blank line, which must match pattern, and its line number."""
        text = lines.line()
        while text is not None and not text.strip():
            text = lines.line()
        if text is None:
            raise self.fail(f"file ends before '{what}' (truncated?)", lines.last)
        match = re.fullmatch(pattern, text.strip(), flags=re.IGNORECASE)
        if match is None:
            raise self.fail(f"expected '{what} <value>', found {text.strip()[:40]!r}", lines.number)
        return match.group(1), lines.number

    def frame_count(self, value: str, line: int) -> int:
        if not (value.isascii() and value.isdigit()):
            raise self.fail(f"Frames: {value!r} is not a whole number", line)
        if int(value) == 0:
            raise self.fail("no frames (Frames: 0)", line)
        if int(value) > 2 ** 53:  # rows of 2 bytes at least: 16 PiB
            raise self.fail(f"Frames: {value} is more rows than any file holds", line)
        return int(value)

    def fps(self, value: str, line: int) -> float:
        frame_time = self.number(value, line, "Frame Time")
        if not (frame_time > 0 and np.isfinite(1.0 / frame_time)):
            raise self.fail(f"Frame Time must be a positive number of seconds, found {value!r}", line)
        return _snap_fps(value, frame_time)

    def motion(self, lines: _Lines, frames: int, layout: _Layout, poses: _Poses | None) -> np.ndarray:
        """Reads the motion rows block by block and returns those of the frames units="auto"
        looks at (_sample_frames), (S, C) float64. With poses, every row is converted, checked
        and handed to poses; without, the rows are only counted and the S rows converted."""
        wanted = _sample_frames(frames)
        samples = np.zeros((len(wanted), layout.count))
        done = 0  # rows read
        while block := lines.block():
            first = lines.number - len(block) + 1  # line number of block[0]
            kept = [i for i, text in enumerate(block) if text.strip()]
            if not kept:
                continue
            lines.last, count = first + kept[-1], len(kept)
            if done + count > frames:
                raise self.fail(f"more motion rows than 'Frames: {frames}' declares", first + kept[frames - done])
            row_frames = np.arange(done, done + count)
            sampled = np.isin(row_frames, wanted)
            if poses is None:
                kept, row_frames = [kept[r] for r in np.flatnonzero(sampled)], row_frames[sampled]
                sampled = sampled[sampled]
            if kept:
                values = self.values([block[i] for i in kept], [first + i for i in kept], row_frames, layout)
                if poses is not None:
                    poses.add(done, values)
                samples[np.searchsorted(wanted, row_frames[sampled])] = values[sampled]
            done += count
        if done < frames and layout.count:
            raise self.fail(f"file ends after {done} of {frames} frames (truncated?)", lines.last or 1)
        return samples

    def values(self, rows: list[str], numbers: list[int], frames: np.ndarray, layout: _Layout) -> np.ndarray:
        """(n, C) float64 values of n motion rows (their line numbers and frame indices (n,)),
        each with C numbers within layout.limits. One numpy conversion for the rows; a value
        that numpy's parser refuses is looked at again by Python's float()."""
        values = None
        if layout.count:
            try:
                values = np.loadtxt(rows, dtype=np.float64, comments=None, ndmin=2)
            except ValueError:
                values = None
        if values is None or values.shape != (len(rows), layout.count):
            values = self.values_one_by_one(rows, numbers, layout.count)
        bad = ~(np.abs(values) <= layout.limits)  # NaN too
        if bad.any():
            r, column = (int(i) for i in np.argwhere(bad)[0])
            raise self.fail(layout.problem(float(values[r, column]), int(frames[r]), column), numbers[r])
        return values

    def values_one_by_one(self, rows: list[str], numbers: list[int], count: int) -> np.ndarray:
        """values' reference path, token by token: names the first row of another length or
        the first value that is no number."""
        values = np.empty((len(rows), count))
        for r, text in enumerate(rows):
            tokens = text.split()
            if len(tokens) != count:
                n = len(tokens)
                raise self.fail(f"motion row has {n} value{'s' * (n != 1)}, the hierarchy has {count} channels", numbers[r])
            values[r] = [self.parse(token, numbers[r], "motion value") for token in tokens]
        return values


def _snap_fps(text: str, frame_time: float) -> float:
    """1 / frame_time, or the integer n when 1/n rounded to the decimals of text is frame_time
    and within 0.1% of it."""
    n = round(1.0 / frame_time)
    try:
        half_unit = 0.5 * 10.0 ** Decimal(text).as_tuple().exponent  # of the last written digit
    except (InvalidOperation, ValueError, TypeError, OverflowError):
        return 1.0 / frame_time
    if n >= 1 and abs(1.0 / n - frame_time) <= half_unit * (1 + 1e-9) and abs(n * frame_time - 1) < 1e-3:
        return float(n)
    return 1.0 / frame_time


def _metres_per_unit(units, extent: float) -> float:
    if isinstance(units, str) and units != "auto":
        if units not in UNITS:
            raise ValueError(f"units must be 'auto', one of {', '.join(UNITS)}, or metres per file unit; got {units!r}")
        return UNITS[units]
    if not isinstance(units, str):
        factor = float(units)
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"units must be a positive number of metres per file unit, got {units!r}")
        return factor
    if not (np.isfinite(extent) and extent > 0):
        return 1.0
    return min(UNITS.values(), key=lambda m: abs(np.log(extent * m / TYPICAL_FIGURE_SIZE)))


def _euler_to_quat(order: str, degrees: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz unit quaternions with w >= 0 of intrinsic rotations by angles (..., len(order))
    in degrees about the axes of order ("ZYX": Rz @ Ry @ Rx), as rot.euler_to_quat gives them:
    the product of the axis quaternions (cos a/2, sin a/2 along the axis), one axis at a time,
    a few tensor operations instead of general quaternion products."""
    half = torch.from_numpy(degrees).movedim(-1, 0).contiguous() * (np.pi / 360)  # (len(order), ...)
    cos, sin = torch.cos(half), torch.sin(half)  # torch's are vectorised, numpy's scalar
    q = [cos[0], torch.zeros_like(cos[0]), torch.zeros_like(cos[0]), torch.zeros_like(cos[0])]  # w, x, y, z
    q[1 + "XYZ".index(order[0])] = sin[0]
    for i, name in enumerate(order[1:], start=1):
        # q (w, v) times (c, s e_a): w' = c w - s v_a, v' = c v + s (w e_a + v x e_a), where
        # v x e_a = (0, v_c, -v_b) in the axes (a, b, c) taken cyclically from a
        a = "XYZ".index(name)
        b, c = (a + 1) % 3, (a + 2) % 3
        w, va, vb, vc = q[0], q[1 + a], q[1 + b], q[1 + c]
        q[0], q[1 + a] = cos[i] * w - sin[i] * va, cos[i] * va + sin[i] * w
        q[1 + b], q[1 + c] = cos[i] * vb + sin[i] * vc, cos[i] * vc - sin[i] * vb
    q = torch.stack(q, dim=-1).numpy()
    q *= np.where(q[..., :1] < 0, -1.0, 1.0)
    return q


def _sample_frames(frames: int) -> np.ndarray:
    """(S,) sorted indices of up to _FIGURE_FRAMES evenly spaced frames of a take of `frames`."""
    count = min(frames, _FIGURE_FRAMES)
    return np.unique(np.linspace(0, frames - 1, count).round().astype(np.int64))


def _figure_size(header: _Header, layout: _Layout, samples: np.ndarray) -> float:
    """Largest extent over axes and the sampled frames' rows (S, C) of joints and end sites (file units)."""
    quats, root, joint_offsets = layout.pose(samples)
    end_parents = [e.parent for e in header.ends]
    end_offsets = np.array([e.offset for e in header.ends], dtype=np.float64).reshape(-1, 3)
    with np.errstate(all="ignore"):
        posed_offsets = layout.offsets if joint_offsets is None else joint_offsets
        r, p = (x.numpy() for x in forward_kinematics(quats, root, posed_offsets, [j.parent for j in header.joints]))
        ends = p[:, end_parents] + (r[:, end_parents] @ end_offsets[..., None])[..., 0]
        points = np.concatenate([p, ends], axis=1)  # (S, J + E, 3)
        return float((points.max(axis=1) - points.min(axis=1)).max())


@contextmanager
def _open(path: str | Path) -> Iterator[tuple[_Reader, _Lines, int]]:
    """The file's reader, its lines (gunzipped when gzip-compressed, judged by content) and
    its uncompressed size in bytes (for gzip, the trailer's: modulo 4 GiB, of the last member)."""
    reader = _Reader(path)
    try:
        raw = open(path, "rb")
    except OSError as error:
        raise reader.fail(f"cannot read file ({error.strerror or error})", None) from None
    with raw:
        try:
            size = os.fstat(raw.fileno()).st_size
            binary = raw
            if raw.read(2) == b"\x1f\x8b" and size >= 4:
                raw.seek(-4, os.SEEK_END)
                size = int.from_bytes(raw.read(4), "little")
                binary = gzip.GzipFile(fileobj=raw, mode="rb")
            raw.seek(0)
            stream = io.TextIOWrapper(binary, encoding="utf-8", errors="surrogateescape", newline=None)
            yield reader, _Lines(reader, stream), size
        except (EOFError, zlib.error, gzip.BadGzipFile) as error:
            raise reader.fail(f"corrupt or truncated gzip data ({error})", None) from None
        except OSError as error:
            raise reader.fail(f"cannot read file ({error.strerror or error})", None) from None


def _scan(path: str | Path, units, keep_frames: bool) -> tuple[_Header, _Layout, _Poses | None, float]:
    """Reads a BVH file: its header, the layout of its rows, its frames (keep_frames) or only
    their count, and metres per file unit (see the module docstring for units)."""
    if units != "auto":
        _metres_per_unit(units, 1.0)  # reject a bad argument before reading
    with _open(path) as (reader, lines, size):
        header = reader.header(lines)
        layout = _Layout.of(header.joints)
        poses = None
        if keep_frames:
            # A row of C values takes at least 2C characters: a Frames: count beyond what the
            # file can hold allocates no more than the file's rows.
            capacity = min(header.frames, (size + 1) // (2 * layout.count) + 1) if layout.count else header.frames
            poses = _Poses(layout, header.frames, capacity)
        samples = reader.motion(lines, header.frames, layout, poses)
    extent = _figure_size(header, layout, samples) if units == "auto" else 1.0
    return header, layout, poses, _metres_per_unit(units, extent)


@dataclass(frozen=True)
class BvhStyle:
    """How a BVH file writes its rig, so that a motion on that rig is written back the same way
    (:func:`write_bvh` style=): units, metres per file unit (0.01 for a centimetre rig), and each
    joint's rotation channel order (joint name -> "ZXY"; joints with fewer than three rotation
    channels are not listed)."""

    units: float = 1.0
    orders: dict[str, str] = field(default_factory=dict)

    def order(self, joint: str) -> str:
        """The joint's own order, else the file's most common one, else ZYX."""
        if joint in self.orders:
            return self.orders[joint]
        counts = list(self.orders.values())
        return max(counts, key=counts.count) if counts else "ZYX"


class _FileRig(NamedTuple):
    """What the file a skeleton was read from said of its rig: its style, and its OFFSET numbers as
    written, in file units (float64: joints (J, 3), end sites (E, 3)). A skeleton holds float32
    metres, about 7 significant digits, and a centimetre rig's 105.214241 has 9, so write_bvh
    writes these back when it writes in the file's own units."""

    style: BvhStyle
    offsets: np.ndarray
    end_offsets: np.ndarray


# The file each skeleton read here came from: write_bvh writes a motion on that skeleton the same
# way (a skeleton is immutable; one made from it, scaled or renamed, has none).
_FROM_FILE: "weakref.WeakKeyDictionary[Skeleton, _FileRig]" = weakref.WeakKeyDictionary()


def _skeleton(path: str | Path, header: _Header, layout: _Layout, scale: float) -> Skeleton:
    """The file's skeleton in metres, end sites named f"{parent}_end", "_end2", ...; its file's
    style and OFFSET numbers remembered (_FROM_FILE)."""
    joints, end_names, seen = header.joints, [], {}
    for end in header.ends:
        seen[end.parent] = seen.get(end.parent, 0) + 1
        end_names.append(f"{joints[end.parent].name}_end" + (str(seen[end.parent]) if seen[end.parent] > 1 else ""))
    end_offsets = np.array([e.offset for e in header.ends], dtype=np.float64).reshape(-1, 3)
    try:
        skeleton = Skeleton([j.name for j in joints], [j.parent for j in joints], layout.offsets * scale,
                            [e.parent for e in header.ends], end_offsets * scale, end_names)
    except ValueError as error:
        raise MotionFileError(path, str(error)) from None
    orders = {joints[j].name: order for order, members, _ in layout.groups if len(order) == 3 for j in members}
    _FROM_FILE[skeleton] = _FileRig(BvhStyle(scale, orders), layout.offsets.copy(), end_offsets)
    return skeleton


def read_bvh(path: str | Path, *, units: str | float = "auto") -> Motion:
    """Read a BVH file (plain or gzip-compressed) into a Motion in metres.

    units: 'auto' (see the module docstring), a name in UNITS ('m', 'cm', 'mm', 'inch', 'cmu'),
        or a float, metres per file unit.
    Returns a Motion with rotations (T, J, 4), root_positions (T, 3) in metres, fps from Frame
    Time, joint_offsets (T, J, 3) metres when non-root joints have position channels (else
    None), and the skeleton's joints in file order. Axes are kept as written (BVH is Y up).
    The rows are read a block at a time into arrays allocated once, so memory stays near the
    Motion's own size (T * J * 16 bytes of rotations) whatever the file's.
    Raises MotionFileError naming the file, the 1-based line and the problem for any malformed
    input (values beyond MAX_ANGLE degrees or MAX_LENGTH file units included); ValueError for a
    bad units argument.
    """
    header, layout, poses, scale = _scan(path, units, keep_frames=True)
    skeleton = _skeleton(path, header, layout, scale)
    joint_offsets = None
    if poses.joint_offsets is not None:
        poses.joint_offsets *= scale
        joint_offsets = torch.from_numpy(poses.joint_offsets)
    try:
        return Motion(skeleton, torch.from_numpy(poses.quats), poses.root * scale, header.fps, joint_offsets, name=file_stem(path, ".bvh"))
    except ValueError as error:
        raise MotionFileError(path, str(error)) from None


@dataclass(frozen=True)
class BvhOutline:
    """What a BVH file holds but its frames' values, as :func:`read_bvh` would read it.

    skeleton: in metres (units chosen as read_bvh chooses them). num_frames: T, the rows counted
    (equal to the file's Frames:). fps from Frame Time. animated_joint_offsets: whether non-root
    joints have position channels (read_bvh then gives joint_offsets). name: the file's stem.
    style: the file's units and rotation orders.
    """

    skeleton: Skeleton
    num_frames: int
    fps: float
    animated_joint_offsets: bool
    name: str
    style: BvhStyle = BvhStyle()

    @property
    def duration(self) -> float:
        """Seconds covered: frames / fps."""
        return self.num_frames / self.fps


def read_bvh_outline(path: str | Path, *, units: str | float = "auto") -> BvhOutline:
    """The skeleton, frame count and frame rate of a BVH file (plain or gzip-compressed),
    without building its rotations: the rows are counted, and only the up to 64 that
    units="auto" looks at are converted and checked. Raises MotionFileError as read_bvh does
    for the header, the row count and those rows."""
    header, layout, _, scale = _scan(path, units, keep_frames=False)
    skeleton = _skeleton(path, header, layout, scale)
    return BvhOutline(skeleton, header.frames, header.fps, bool(layout.moved), file_stem(path, ".bvh"), _FROM_FILE[skeleton].style)


def bvh_style(path: str | Path, *, units: str | float = "auto") -> BvhStyle:
    """The units and rotation orders of a BVH file (units as read_bvh chooses them), to write a
    motion on its rig as the file does: write_bvh(motion, out, style=bvh_style(rig_file))."""
    return read_bvh_outline(path, units=units).style


def write_bvh(motion: Motion, path: str | Path, *, euler_order: str | None = None, precision: int = 6,
              style: BvhStyle | None = None) -> None:
    """Write a Motion as a BVH file; gzip-compressed when path ends in .gz.

    A rig is written as it is: a motion on a skeleton read from a BVH file (read_bvh, and
    what keeps that skeleton: slices, resampling, a retarget onto it) is written in that file's
    units and rotation orders, so a centimetre rig in ZXY stays centimetres in ZXY. Others: metres,
    ZYX. style (:func:`bvh_style`; BvhStyle() for metres and ZYX) overrides this: lengths in its
    units, each joint in its rotation order (joints it does not list in its most common one).
    euler_order: one order for every joint, overriding the style's.

    The root gets OFFSET 0 0 0 and 6 channels: its world position, then rotations (intrinsic
    orders, e.g. "ZYX" = "Zrotation Yrotation Xrotation", degrees). A zero root
    OFFSET reads the same whether a reader adds the root channels to the OFFSET (read_bvh) or
    replaces it (Blender). Other joints get OFFSET = skeleton offset and 3 rotation
    channels, or 6 (positions from motion.joint_offsets first) when joint_offsets is not None.
    End sites become End Site blocks. Joints are written depth-first, children in index order,
    which is the order read_bvh gives back (the input's own order for any skeleton read from BVH);
    blocks are indented one tab per level, up to _MAX_INDENT tabs.
    precision: decimals of every number written. The file is written under a temporary name
    beside path and renamed, so a failure never leaves a half-written file.
    """
    read = _FROM_FILE.get(motion.skeleton)
    style = style or (read.style if read else None)
    orders = [euler_order or (style.order(n) if style else "ZYX") for n in motion.skeleton.names]
    for each in set(orders):
        if len(each) != 3 or sorted(each) != ["X", "Y", "Z"]:
            raise ValueError(f"euler_order must be an intrinsic order such as 'ZYX' (a permutation of XYZ), got {each!r}")
    unit = style.units if style else 1.0
    skeleton = motion.skeleton
    if read is not None and read.style.units == unit:       # the file's own numbers
        offsets, end_offsets = read.offsets, read.end_offsets
    else:                                                   # the skeleton's float32 metres in file units
        offsets, end_offsets = (x.double().numpy() / unit for x in (skeleton.offsets, skeleton.end_site_offsets))
    for name in skeleton.names:
        if not name or re.search(r"[\s{}]", name):
            raise ValueError(f"joint name {name!r} cannot be written to BVH (empty, or holds whitespace or braces); rename it")
    moved = motion.joint_offsets is not None

    def numbers(values) -> str:
        return " ".join(f"{x:.{precision}f}" for x in values)

    children: list[list[int]] = [[] for _ in skeleton.names]
    for j, p in enumerate(skeleton.parents[1:], start=1):
        children[p].append(j)
    end_sites: list[list[int]] = [[] for _ in skeleton.names]
    for e, p in enumerate(skeleton.end_site_parents):
        end_sites[p].append(e)
    depth = skeleton.depth().tolist()
    text, order = ["HIERARCHY"], []  # order: the joints as written
    stack = [(0, False)]  # (joint, whether its block is to be closed): depth-first without recursion
    while stack:
        j, closing = stack.pop()
        pad = "\t" * min(depth[j], _MAX_INDENT)
        if closing:
            for e in end_sites[j]:
                text.extend([pad + "\tEnd Site", pad + "\t{",
                             pad + "\t\tOFFSET " + numbers(end_offsets[e]), pad + "\t}"])
            text.append(pad + "}")
            continue
        text.extend([pad + ("ROOT " if j == 0 else "JOINT ") + skeleton.names[j], pad + "{",
                     pad + "\tOFFSET " + numbers((0.0, 0.0, 0.0) if j == 0 else offsets[j])])
        rotation_channels = " ".join(f"{axis}rotation" for axis in orders[j])
        if j == 0 or moved:
            text.append(pad + f"\tCHANNELS 6 Xposition Yposition Zposition {rotation_channels}")
        else:
            text.append(pad + f"\tCHANNELS 3 {rotation_channels}")
        order.append(j)
        stack.append((j, True))
        stack.extend((child, False) for child in reversed(children[j]))

    text += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {1.0 / motion.fps:.10g}"]
    row = " ".join([f"%.{precision}f"] * (6 * len(order) if moved else 3 + 3 * len(order))) + "\n"

    def values(frames: slice) -> np.ndarray:
        """(n, C) motion rows of the frames: positions in file units, angles in degrees."""
        quats = torch.nn.functional.normalize(motion.rotations[frames].detach().cpu().double(), dim=-1)
        euler = torch.empty(quats.shape[:-1] + (3,), dtype=torch.float64)
        for each in set(orders):
            joints = [j for j, o in enumerate(orders) if o == each]
            euler[:, joints] = rot.quat_to_euler(each, quats[:, joints], degrees=True)
        euler = euler[:, order]  # (n, J, 3)
        root = motion.root_positions[frames].detach().cpu().double() / unit
        if moved:  # every joint: its position, then its rotation
            positions = motion.joint_offsets[frames].detach().cpu().double() / unit
            positions[:, 0] = root
            return torch.cat([positions[:, order], euler], dim=-1).flatten(1).numpy()
        return torch.cat([root, euler.flatten(1)], dim=1).numpy()

    def chunks() -> Iterator[bytes]:
        """The text _WRITE_ROWS rows at a time: neither the file nor all its rows is ever in memory."""
        yield ("\n".join(text) + "\n").encode("utf-8")
        for start in range(0, motion.num_frames, _WRITE_ROWS):
            rows = values(slice(start, start + _WRITE_ROWS)).tolist()
            yield "".join(row % tuple(r) for r in rows).encode()

    write_atomic(path, chunks())
