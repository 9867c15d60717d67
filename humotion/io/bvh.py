"""BVH (Biovision Hierarchy) motion files: read one into a Motion, write a Motion as one.

Why a parser of our own: the BVH packages on PyPI build a Python object per joint and convert the
motion block value by value (seconds for a long take), report malformed input with bare
IndexError/ValueError and no line number, do not read gzip, and fix conventions we need to
control: per-joint channel orders, position channels on non-root joints, length units. Here the
small hierarchy is read line by line and the motion block with one numpy conversion.

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
  files give Motion.joint_offsets (F, J, 3); when only the root has position channels it is None.
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
"""

from __future__ import annotations

import gzip
import os
import re
import tempfile
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from itertools import chain
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, OutputPathError, read_text
from humotion.motion import Motion
from humotion.skeleton import Skeleton, forward_kinematics

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254, "cmu": 0.0254 / 0.45}
"""Metres per file unit for each name units= accepts. 'cmu': CMU's ASF unit, 1/0.45 inch."""

TYPICAL_FIGURE_SIZE = 1.7  # metres; what units="auto" aims at

_CHANNEL_NAMES = {f"{axis}{kind}": (kind, "XYZ".index(axis.upper()))
                  for axis in "xyz" for kind in ("position", "rotation")}


@dataclass(eq=False)
class _Block:
    """A ROOT/JOINT or End Site as read from the hierarchy (lengths in file units)."""

    kind: str  # "joint" or "end"
    name: str
    parent: int
    line: int
    offset: list[float] | None = None
    channels: list[tuple[str, int]] = field(default_factory=list)  # (kind, axis) in file order
    has_channels: bool = False


class _Reader:
    """Raises MotionFileError for one file; keeps the path out of every call."""

    def __init__(self, path):
        self.path = path

    def fail(self, problem: str, line: int | None) -> MotionFileError:
        return MotionFileError(self.path, problem, line=line)

    def number(self, token: str, line: int, what: str) -> float:
        try:
            value = float(token)
        except ValueError:
            raise self.fail(f"{what}: {token!r} is not a number", line) from None
        if not np.isfinite(value):
            raise self.fail(f"{what}: {token!r} is not a finite number", line)
        return value

    # -- hierarchy ------------------------------------------------------------------------
    def hierarchy(self, lines: list[str]) -> tuple[list[_Block], list[_Block], int]:
        """Joints (file order), end sites, and the index of the MOTION line."""
        joints: list[_Block] = []
        ends: list[_Block] = []
        stack: list[_Block] = []  # open blocks
        pending: _Block | None = None  # waiting for its "{"
        started = False
        for index, text in enumerate(lines):
            line = index + 1
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
                    if any(j.name == name for j in joints):
                        raise self.fail(f"duplicate joint name {name!r}", line)
                    parent = joints.index(stack[-1]) if word == "JOINT" else -1
                    pending = _Block("joint", name, parent, line)
                    joints.append(pending)
                elif word == "END":
                    if not args or args[0].upper() != "SITE":
                        raise self.fail("expected 'End Site'", line)
                    if not stack or stack[-1].kind != "joint":
                        raise self.fail("End Site outside a ROOT or JOINT block", line)
                    pending = _Block("end", "", joints.index(stack[-1]), line)
                    ends.append(pending)
                elif word == "OFFSET":
                    if not stack:
                        raise self.fail("OFFSET outside a ROOT, JOINT or End Site block", line)
                    if stack[-1].offset is not None:
                        raise self.fail("a second OFFSET in one block", line)
                    if len(args) != 3:
                        raise self.fail(f"OFFSET needs 3 numbers, found {len(args)}", line)
                    stack[-1].offset = [self.number(a, line, "OFFSET") for a in args]
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
                    return joints, ends, index
                else:
                    raise self.fail(f"unknown keyword {token!r} in the hierarchy", line)
                k = stop
        if stack or pending is not None:
            raise self.fail("file ends inside the hierarchy (truncated?)", _last_line(lines))
        raise self.fail("no MOTION section", _last_line(lines))

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
    def header_value(self, lines: list[str], start: int, pattern: str, what: str) -> tuple[str, int]:
        """The value of the next non-blank line matching pattern, and that line's index."""
        index = next((i for i in range(start, len(lines)) if lines[i].strip()), None)
        if index is None:
            raise self.fail(f"file ends before '{what}' (truncated?)", _last_line(lines))
        match = re.fullmatch(pattern, lines[index].strip(), flags=re.IGNORECASE)
        if match is None:
            raise self.fail(f"expected '{what} <value>', found {lines[index].strip()[:40]!r}", index + 1)
        return match.group(1), index

    def frame_count(self, value: str, line: int) -> int:
        if not (value.isascii() and value.isdigit()):
            raise self.fail(f"Frames: {value!r} is not a whole number", line)
        if int(value) == 0:
            raise self.fail("no frames (Frames: 0)", line)
        return int(value)

    def fps(self, value: str, line: int) -> float:
        frame_time = self.number(value, line, "Frame Time")
        if not (frame_time > 0 and np.isfinite(1.0 / frame_time)):
            raise self.fail(f"Frame Time must be a positive number of seconds, found {value!r}", line)
        return _snap_fps(value, frame_time)

    def values(self, lines: list[str], first: int, frames: int, joints: list[_Block]) -> np.ndarray:
        """(frames, channels) float64 from the rows after the header: one numpy conversion."""
        channels = sum(len(j.channels) for j in joints)
        rows = [i for i in range(first, len(lines)) if lines[i].strip()]
        if channels == 0 and not rows:  # no joint has channels: the frames are all rest poses
            return np.zeros((frames, 0))
        split = [lines[i].split() for i in rows]
        counts = np.fromiter(map(len, split), dtype=np.int64, count=len(split))
        wrong = np.flatnonzero(counts != channels)
        if len(wrong):
            r = int(wrong[0])
            n = int(counts[r])
            raise self.fail(f"motion row has {n} value{'s' * (n != 1)}, the hierarchy has {channels} channels", rows[r] + 1)
        if len(rows) < frames:
            raise self.fail(f"file ends after {len(rows)} of {frames} frames (truncated?)", _last_line(lines))
        if len(rows) > frames:
            raise self.fail(f"more motion rows than 'Frames: {frames}' declares", rows[frames] + 1)
        try:
            values = np.array(list(chain.from_iterable(split)), dtype=np.float64)
        except ValueError:
            for r, tokens in enumerate(split):  # error path only: find the culprit
                for token in tokens:
                    self.number(token, rows[r] + 1, "motion value")
            raise self.fail("motion block holds a value that is not a number", rows[0] + 1) from None
        values = values.reshape(frames, channels)
        bad = np.argwhere(~np.isfinite(values))
        if len(bad):
            frame, column = (int(i) for i in bad[0])
            joint, (kind, axis) = [(j.name, c) for j in joints for c in j.channels][column]
            raise self.fail(f"motion row holds NaN or infinity (frame {frame}, joint {joint!r}, "
                            f"channel {'XYZ'[axis]}{kind})", rows[frame] + 1)
        return values


def _last_line(lines: list[str]) -> int:
    """1-based number of the last line holding anything but whitespace."""
    return next((i + 1 for i in range(len(lines) - 1, -1, -1) if lines[i].strip()), 1)


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


def _figure_size(quats, root, offsets, joint_offsets, parents, end_parents, end_offsets) -> float:
    """Largest extent over axes and up to 64 evenly spaced frames of joints and end sites (file units)."""
    frames = np.unique(np.linspace(0, len(root) - 1, min(len(root), 64)).round().astype(np.int64))
    with np.errstate(all="ignore"):
        posed_offsets = offsets if joint_offsets is None else joint_offsets[frames]
        r, p = forward_kinematics(quats[frames].numpy(), root[frames], posed_offsets, parents)
        ends = p[:, end_parents] + (r[:, end_parents] @ end_offsets[..., None])[..., 0]
        points = np.concatenate([p, ends], axis=1)  # (frames, J + E, 3)
        return float((points.max(axis=1) - points.min(axis=1)).max())


def read_bvh(path: str | Path, *, units: str | float = "auto") -> Motion:
    """Read a BVH file (plain or gzip-compressed) into a Motion in metres.

    units: 'auto' (see the module docstring), a name in UNITS ('m', 'cm', 'mm', 'inch', 'cmu'),
        or a float, metres per file unit.
    Returns a Motion with rotations (F, J, 4), root_positions (F, 3) in metres, fps from Frame
    Time, joint_offsets (F, J, 3) metres when non-root joints have position channels (else
    None), and the skeleton's joints in file order. Axes are kept as written (BVH is Y up).
    Raises MotionFileError naming the file, the 1-based line and the problem for any malformed
    input; ValueError for a bad units argument.
    """
    if units != "auto":
        _metres_per_unit(units, 1.0)  # reject a bad argument before reading
    reader = _Reader(path)
    lines = read_text(path).lstrip("\ufeff").replace("\r\n", "\n").replace("\r", "\n").split("\n")
    joints, ends, motion_index = reader.hierarchy(lines)
    value, index = reader.header_value(lines, motion_index + 1, r"frames\s*:?\s*(\S+)", "Frames:")
    frames = reader.frame_count(value, index + 1)
    value, index = reader.header_value(lines, index + 1, r"frame\s*time\s*:?\s*(\S+)", "Frame Time:")
    fps = reader.fps(value, index + 1)
    values = reader.values(lines, index + 1, frames, joints)

    offsets = np.array([j.offset for j in joints], dtype=np.float64)
    root = np.tile(offsets[0], (frames, 1))
    joint_offsets = None
    rotation_groups: dict[str, list[tuple[int, list[int]]]] = {}
    column = 0
    for j, joint in enumerate(joints):
        order, rotation_columns = "", []
        for kind, axis in joint.channels:
            if kind == "rotation":
                order += "XYZ"[axis]
                rotation_columns.append(column)
            elif j == 0:
                root[:, axis] += values[:, column]
            else:
                if joint_offsets is None:
                    joint_offsets = np.tile(offsets, (frames, 1, 1))
                joint_offsets[:, j, axis] = values[:, column]
            column += 1
        if order:
            rotation_groups.setdefault(order, []).append((j, rotation_columns))
    quats = rot.quat_identity(frames, len(joints), dtype=torch.float64)
    for order, members in rotation_groups.items():
        indices = [j for j, _ in members]
        angles = torch.from_numpy(values[:, [c for _, c in members]])  # (F, k, len(order)) degrees
        quats[:, indices] = rot.euler_to_quat(order, angles, degrees=True)

    end_offsets = np.array([e.offset for e in ends], dtype=np.float64).reshape(-1, 3)
    end_parents = [e.parent for e in ends]
    parents = [j.parent for j in joints]
    scale = _metres_per_unit(units, _figure_size(quats, root, offsets, joint_offsets, parents, end_parents, end_offsets))

    end_names, seen = [], {}
    for p in end_parents:
        seen[p] = seen.get(p, 0) + 1
        end_names.append(f"{joints[p].name}_end" + (str(seen[p]) if seen[p] > 1 else ""))
    name = Path(path).name
    for suffix in (".gz", ".bvh"):
        name = name[:-len(suffix)] if name.lower().endswith(suffix) else name
    try:
        skeleton = Skeleton([j.name for j in joints], parents, offsets * scale, end_parents,
                            end_offsets * scale, end_names)
        return Motion(skeleton, quats.float(), root * scale, fps,
                      None if joint_offsets is None else joint_offsets * scale, name=name)
    except ValueError as error:  # e.g. values beyond float32 range
        raise MotionFileError(path, str(error)) from None


def write_bvh(motion: Motion, path: str | Path, *, euler_order: str = "ZYX", precision: int = 6) -> None:
    """Write a Motion as a BVH file, lengths in metres; gzip-compressed when path ends in .gz.

    The root gets OFFSET 0 0 0 and 6 channels: its world position (metres), then rotations in
    euler_order (intrinsic, e.g. "ZYX" = "Zrotation Yrotation Xrotation", degrees). A zero root
    OFFSET reads the same whether a reader adds the root channels to the OFFSET (read_bvh) or
    replaces it (Blender). Other joints get OFFSET = skeleton offset (metres) and 3 rotation
    channels, or 6 (positions from motion.joint_offsets first) when joint_offsets is not None.
    End sites become End Site blocks. Joints are written depth-first, children in index order,
    which is the order read_bvh gives back (the input's own order for any skeleton read from BVH).
    precision: decimals of every number written. The file is written under a temporary name
    beside path and renamed, so a failure never leaves a half-written file.
    """
    if len(euler_order) != 3 or sorted(euler_order) != ["X", "Y", "Z"]:
        raise ValueError(f"euler_order must be an intrinsic order such as 'ZYX' (a permutation of XYZ), got {euler_order!r}")
    skeleton = motion.skeleton
    for name in skeleton.names:
        if not name or re.search(r"[\s{}]", name):
            raise ValueError(f"joint name {name!r} cannot be written to BVH (empty, or holds whitespace or braces); rename it")
    quats = torch.nn.functional.normalize(motion.rotations.detach().cpu().double(), dim=-1)
    euler = rot.quat_to_euler(euler_order, quats, degrees=True).numpy()  # (F, J, 3) degrees
    root = motion.root_positions.detach().cpu().double().numpy()
    joint_offsets = None if motion.joint_offsets is None else motion.joint_offsets.detach().cpu().double().numpy()
    rotation_channels = " ".join(f"{axis}rotation" for axis in euler_order)

    def numbers(values) -> str:
        return " ".join(f"{x:.{precision}f}" for x in values)

    text, columns = ["HIERARCHY"], []

    def write_joint(j: int, depth: int) -> None:
        pad = "\t" * depth
        text.extend([pad + ("ROOT " if j == 0 else "JOINT ") + skeleton.names[j], pad + "{",
                     pad + "\tOFFSET " + numbers((0.0, 0.0, 0.0) if j == 0 else skeleton.offsets[j])])
        if j == 0 or joint_offsets is not None:
            text.append(pad + f"\tCHANNELS 6 Xposition Yposition Zposition {rotation_channels}")
            columns.append(root if j == 0 else joint_offsets[:, j])
        else:
            text.append(pad + f"\tCHANNELS 3 {rotation_channels}")
        columns.append(euler[:, j])
        for child in skeleton.children(j):
            write_joint(child, depth + 1)
        for e, parent in enumerate(skeleton.end_site_parents):
            if parent == j:
                text.extend([pad + "\tEnd Site", pad + "\t{",
                             pad + "\t\tOFFSET " + numbers(skeleton.end_site_offsets[e]), pad + "\t}"])
        text.append(pad + "}")

    write_joint(0, 0)
    text += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {1.0 / motion.fps:.10g}"]
    data = np.concatenate(columns, axis=1)  # (F, channels)
    row = " ".join([f"%.{precision}f"] * data.shape[1])
    text += [row % tuple(values) for values in data.tolist()]
    _write_atomic(Path(path), ("\n".join(text) + "\n").encode("utf-8"))


def _write_atomic(path: Path, data: bytes) -> None:
    """data (gzip-compressed for a .gz name) into a temporary file beside path, renamed onto path:
    path holds its old bytes or all the new ones, never a part. OutputPathError naming path, not
    the temporary file, when it cannot be written."""
    if path.name.lower().endswith(".gz"):
        data = gzip.compress(data, compresslevel=6, mtime=0)
    temporary = None
    try:
        mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
        handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException as error:
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise OutputPathError(path, f"cannot write the file ({error.strerror or error})") from None
        raise
