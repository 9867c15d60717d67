"""Acclaim ASF/AMC: the skeleton (.asf) and motion (.amc) files of the CMU and HDM05 databases.

Why a parser of our own: no maintained PyPI package reads ASF/AMC with what humotion needs:
every bone's dof list (any subset and order of rx ry rz tx ty tz l), its axis rotation in any
axis order, joint limits, the root's channel order, units, gzip, and errors that name the file
and line. The format is small (Acclaim's 1994 spec, as written by VICON BodyBuilder), so it is
parsed here directly.

How the file maps onto humotion's Skeleton (metres, Y up, +Z forward; the CMU/HDM05 ASF axes
already are Y up, +Z forward, a character's left = +X, so no axis change is needed):

- joints are the root plus one joint per bone, named by the bone, each located at its bone's
  START; a joint's rotation turns its own bone. So joint "lfemur" is the hip and "ltibia" the
  knee. The offset of a joint is its parent bone's direction * length (the root's children sit
  on the root). A bone with no children gets an end site "<bone>_end" at its end.
- lengths: ``:units length L`` means one file unit is 1/L inch (CMU FAQ: metres =
  value * (1/0.45) * 0.0254 for L = 0.45), for bone lengths and root translations alike.
- every bone's rest orientation is the world's (ASF directions are world vectors), so the local
  rotation of a joint is ``C @ M @ C^-1``, C the bone's ``axis`` rotation and M the AMC motion
  rotation built from the frame's dof values. Both are Euler angles composed in the written
  order, each later rotation about the fixed (world/parent) axes: "rx ry rz" gives
  M = Rz @ Ry @ Rx (roma's extrinsic convention "xyz"), and "axis ax ay az XYZ" likewise gives
  C = Rz(az) @ Ry(ay) @ Rx(ax). This is what the CMU/USC mocap player does, and
  tests/test_amc_vs_bvh.py proves it against CMU's BVH conversion of the same take, read by
  humotion.io.bvh: hips, legs and lower spine agree to 0.01 mm on all 2751 frames of 01_01,
  where the intrinsic reading ("XYZ", M = Rx @ Ry @ Rz) puts an ankle up to 1.65 m off.
- the root: position from its TX TY TZ channels plus the ASF root ``position``; rotation from its
  RX RY RZ channels in the ``order`` given, conjugated by the ``orientation``/``axis`` rotation
  in the same way as a bone.
- bone translation dofs (tx ty tz, rare) move the joint by C @ t in its parent's frame, and "l"
  stretches the bone along its direction (its child joints move; end sites keep the rest length);
  both become Motion.joint_offsets.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, read_text
from humotion.motion import Motion
from humotion.skeleton import Skeleton

__all__ = ["AsfSkeleton", "read_asf", "read_amc", "find_asf", "INCH"]

INCH = 0.0254  # metres
_ROTATION_DOFS = ("rx", "ry", "rz")
_TRANSLATION_DOFS = ("tx", "ty", "tz")
_DOFS = _ROTATION_DOFS + _TRANSLATION_DOFS + ("l",)
_BONE_FIELDS = ("name", "direction", "length", "axis")  # required in every bonedata block


@dataclass(frozen=True, eq=False)
class AsfSkeleton:
    """An ASF file: the humotion Skeleton plus what the AMC reader and joint limits need.

    skeleton: joints = "root" + one per bone (at the bone's start), metres; end sites at the
        ends of leaf bones.
    dofs: joint name -> its channels in file order, lower case ("rx", "ry", "rz", "tx", "ty",
        "tz", "l"); the root's come from ``:root order`` (e.g. ("tx", "ty", "tz", "rx", "ry", "rz")).
        Joints without dofs map to ().
    limits: joint name -> one (min, max) per dof: degrees for rotations, metres for
        translations and "l"; (-inf, inf) where the file gives no limits.
    axis_angles: joint name -> (3,) axis angles (x, y, z) in degrees, as written (the root's is
        its ``orientation``).
    axis_orders: joint name -> axis order as written ("XYZ"); the first letter's rotation is
        applied first.
    axis_rotations: (J, 4) wxyz quaternion C of each joint's axis (joint order of skeleton).
    root_position: (3,) the ASF root ``position``, metres.
    units: the ``:units`` section as read: {"length": 0.45, "angle": "deg", "mass": 1.0, ...}.
    metres_per_unit: metres per file length unit (INCH / units["length"]).
    directions, lengths: joint name -> bone direction (3,) and length in metres (root: zeros, 0).
    """

    skeleton: Skeleton
    dofs: dict[str, tuple[str, ...]]
    limits: dict[str, tuple[tuple[float, float], ...]]
    axis_angles: dict[str, np.ndarray]
    axis_orders: dict[str, str]
    axis_rotations: np.ndarray
    root_order: tuple[str, ...]
    root_axis: str
    root_position: np.ndarray
    units: dict[str, float | str]
    metres_per_unit: float
    directions: dict[str, np.ndarray] = field(default_factory=dict)
    lengths: dict[str, float] = field(default_factory=dict)
    name: str = ""
    path: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return self.skeleton.names

    def __repr__(self) -> str:
        return (f"AsfSkeleton({self.name!r}, {self.skeleton.num_joints} joints, "
                f"{sum(len(d) for d in self.dofs.values())} dofs, height={self.skeleton.height():.2f} m)")


# ----------------------------------------------------------------------------------------------
# ASF
# ----------------------------------------------------------------------------------------------
def _floats(path, tokens, line, what, count=None) -> list[float]:
    if count is not None and len(tokens) != count:
        raise MotionFileError(path, f"{what} needs {count} numbers, found {len(tokens)}", line=line)
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise MotionFileError(path, f"{what}: non-numeric value in {' '.join(tokens)!r}", line=line) from None
    if count is not None and not all(math.isfinite(v) for v in values):
        raise MotionFileError(path, f"{what}: NaN or infinite value in {' '.join(tokens)!r}", line=line)
    return values


def _axis_order(path, token, line) -> str:
    order = token.upper()
    if len(order) != 3 or sorted(order) != ["X", "Y", "Z"]:
        raise MotionFileError(path, f"axis order {token!r} is not a permutation of XYZ", line=line)
    return order


def _check_dofs(path, dofs, line, what) -> tuple[str, ...]:
    dofs = tuple(d.lower() for d in dofs)
    for d in dofs:
        if d not in _DOFS:
            raise MotionFileError(path, f"{what}: unknown dof {d!r} (known: {' '.join(_DOFS)})", line=line)
    if len(set(dofs)) != len(dofs):
        raise MotionFileError(path, f"{what}: repeated dof in {' '.join(dofs)!r}", line=line)
    return dofs


def read_asf(path: str | Path) -> AsfSkeleton:
    """Read an Acclaim skeleton (.asf, optionally gzip-compressed) into an AsfSkeleton.

    Raises MotionFileError (file, line, problem) for anything it cannot read: missing bonedata
    fields, unknown names or cycles in :hierarchy, bones left out of the hierarchy, malformed
    numbers, dof/limit count mismatches.
    """
    path = Path(path)
    lines = read_text(path).split("\n")
    units: dict[str, float | str] = {"length": 1.0, "angle": "deg", "mass": 1.0}
    root = {"order": ("tx", "ty", "tz", "rx", "ry", "rz"), "axis": "XYZ", "position": [0.0] * 3,
            "orientation": [0.0] * 3}
    bones: dict[str, dict] = {}
    children: dict[str, list[str]] = {}
    hierarchy_parent: dict[str, str] = {}
    section = None
    bone: dict | None = None
    in_hierarchy_block = False
    last_key = None
    seen_sections = set()

    for index, raw in enumerate(lines):
        lineno = index + 1
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        tokens = text.split()
        key = tokens[0].lower()
        if text.startswith(":"):
            if bone is not None:
                raise MotionFileError(path, f"bone block opened at line {bone['line']} has no 'end'", line=lineno)
            section = key[1:]
            seen_sections.add(section)
            last_key = None
            if section in ("units", "root", "bonedata", "hierarchy") and len(tokens) > 1:
                raise MotionFileError(path, f"unexpected text after {tokens[0]}", line=lineno)
            continue  # :version, :name, :documentation and unknown sections carry nothing we use
        if section == "units":
            if len(tokens) != 2:
                raise MotionFileError(path, f"units line should be 'name value', got {text!r}", line=lineno)
            if key == "angle":
                unit = tokens[1].lower()
                if unit not in ("deg", "rad"):
                    raise MotionFileError(path, f"angle unit {tokens[1]!r} is neither 'deg' nor 'rad'", line=lineno)
                units["angle"] = unit
            else:
                value = _floats(path, tokens[1:], lineno, f"units {key}", 1)[0]
                if key == "length" and not value > 0:
                    raise MotionFileError(path, f"length unit must be positive, got {value}", line=lineno)
                units[key] = value
        elif section == "root":
            if key == "order":
                order = tuple(t.lower() for t in tokens[1:])
                _check_dofs(path, order, lineno, "root order")
                if any(d == "l" for d in order):
                    raise MotionFileError(path, "root order cannot contain 'l'", line=lineno)
                root["order"] = order
            elif key == "axis":
                if len(tokens) != 2:
                    raise MotionFileError(path, f"root axis should be one order like XYZ, got {text!r}", line=lineno)
                root["axis"] = _axis_order(path, tokens[1], lineno)
            elif key in ("position", "orientation"):
                root[key] = _floats(path, tokens[1:], lineno, f"root {key}", 3)
            else:
                raise MotionFileError(path, f"unknown root field {tokens[0]!r}", line=lineno)
        elif section == "bonedata":
            if key == "begin":
                if bone is not None:
                    raise MotionFileError(path, f"'begin' inside the bone block opened at line {bone['line']}", line=lineno)
                bone = {"line": lineno, "dof": (), "limits": None}
                last_key = None
                continue
            if bone is None:
                raise MotionFileError(path, f"bonedata field {tokens[0]!r} outside a begin/end block", line=lineno)
            if key == "end":
                missing = [f for f in _BONE_FIELDS if f not in bone]
                if missing:
                    raise MotionFileError(path, f"bone block has no {', '.join(missing)}", line=bone["line"])
                if bone["limits"] is not None and len(bone["limits"]) != len(bone["dof"]):
                    raise MotionFileError(path, f"bone {bone['name']!r} has {len(bone['dof'])} dofs but "
                                          f"{len(bone['limits'])} limits", line=bone["limits_line"])
                if bone["name"] in bones or bone["name"] == "root":
                    problem = "is reserved for the root" if bone["name"] == "root" else "is used twice"
                    raise MotionFileError(path, f"bone name {bone['name']!r} {problem}", line=bone["name_line"])
                bones[bone["name"]] = bone
                bone = None
                continue
            if text.startswith("(") and last_key == "limits":
                bone["limits_text"] += " " + text
                bone["limits"] = _parse_limits(path, bone["limits_text"], lineno)
                continue
            last_key = key
            if key == "id":
                continue
            if key == "name":
                if len(tokens) != 2:
                    raise MotionFileError(path, f"bone name should be one word, got {text!r}", line=lineno)
                bone["name"], bone["name_line"] = tokens[1], lineno
            elif key == "direction":
                bone["direction"] = _floats(path, tokens[1:], lineno, "direction", 3)
            elif key == "length":
                bone["length"] = _floats(path, tokens[1:], lineno, "length", 1)[0]
            elif key == "axis":
                if len(tokens) != 5:
                    raise MotionFileError(path, f"axis should be 'axis ax ay az ORDER', got {text!r}", line=lineno)
                bone["axis"] = _floats(path, tokens[1:4], lineno, "axis", 3)
                bone["axis_order"] = _axis_order(path, tokens[4], lineno)
            elif key == "dof":
                bone["dof"] = _check_dofs(path, tokens[1:], lineno, "dof")
            elif key == "limits":
                bone["limits_text"], bone["limits_line"] = text[len(tokens[0]):], lineno
                bone["limits"] = _parse_limits(path, bone["limits_text"], lineno)
            elif key in ("bodymass", "cofmass"):
                continue
            else:
                raise MotionFileError(path, f"unknown bonedata field {tokens[0]!r}", line=lineno)
        elif section == "hierarchy":
            if key == "begin":
                in_hierarchy_block = True
                continue
            if key == "end":
                in_hierarchy_block = False
                continue
            if not in_hierarchy_block:
                raise MotionFileError(path, f"hierarchy line outside begin/end: {text!r}", line=lineno)
            parent = tokens[0]
            if parent != "root" and parent not in bones:
                raise MotionFileError(path, f"unknown parent {parent!r} in :hierarchy (not a bone in :bonedata)", line=lineno)
            if len(tokens) < 2:
                raise MotionFileError(path, f"hierarchy line names parent {parent!r} but no children", line=lineno)
            for child in tokens[1:]:
                if child not in bones:
                    raise MotionFileError(path, f"unknown child {child!r} in :hierarchy (not a bone in :bonedata)", line=lineno)
                if child in hierarchy_parent:
                    raise MotionFileError(path, f"bone {child!r} is given a second parent ({parent!r}, "
                                          f"already under {hierarchy_parent[child]!r})", line=lineno)
                hierarchy_parent[child] = parent
                children.setdefault(parent, []).append(child)
        elif section is None:
            raise MotionFileError(path, f"text before the first ':section' line: {text!r}", line=lineno)
        # text in ignored sections (:version, :name, :documentation, unknown) is skipped

    if bone is not None:
        raise MotionFileError(path, f"bone block opened at line {bone['line']} has no 'end'", line=len(lines))
    if "bonedata" not in seen_sections and "hierarchy" not in seen_sections:
        raise MotionFileError(path, "not an ASF file: no :bonedata or :hierarchy section")
    if in_hierarchy_block:
        raise MotionFileError(path, ":hierarchy block has no 'end'", line=len(lines))

    # Depth-first order from the root, children in file order: parents before children.
    order: list[str] = ["root"]
    parent_of = hierarchy_parent
    stack = list(reversed(children.get("root", [])))
    visited = {"root"}
    while stack:
        name = stack.pop()
        if name in visited:  # only reachable through a cycle
            raise MotionFileError(path, f"the :hierarchy contains a cycle through {name!r}")
        visited.add(name)
        order.append(name)
        stack.extend(reversed(children.get(name, [])))
    unreached = [b for b in bones if b not in visited]
    if unreached:
        raise MotionFileError(path, f"bones not connected to the root in :hierarchy: {', '.join(unreached)}")

    metres = INCH / float(units["length"])
    degrees = units["angle"] == "deg"
    index = {n: i for i, n in enumerate(order)}
    offsets = np.zeros((len(order), 3))
    offsets[0] = np.asarray(root["position"]) * metres
    directions = {"root": np.zeros(3)}
    lengths = {"root": 0.0}
    for name in order[1:]:
        b = bones[name]
        directions[name] = np.asarray(b["direction"], dtype=np.float64)
        lengths[name] = b["length"] * metres
        parent = parent_of[name]
        if parent != "root":
            offsets[index[name]] = directions[parent] * lengths[parent]
    leaves = [n for n in order[1:] if not children.get(n)]
    try:
        skeleton = Skeleton(
            names=order,
            parents=[-1] + [index[parent_of[n]] for n in order[1:]],
            offsets=offsets,
            end_site_parents=[index[n] for n in leaves],
            end_site_offsets=np.array([directions[n] * lengths[n] for n in leaves]).reshape(-1, 3),
            end_site_names=[f"{n}_end" for n in leaves],
        )
    except ValueError as error:  # e.g. lengths so large they overflow
        raise MotionFileError(path, f"bad skeleton: {error}") from None

    def to_limits(dofs, lims):
        if lims is None:
            return tuple((-math.inf, math.inf) for _ in dofs)
        out = []
        for d, (lo, hi) in zip(dofs, lims):
            if d in _ROTATION_DOFS:
                lo, hi = (lo, hi) if degrees else (math.degrees(lo), math.degrees(hi))
            else:
                lo, hi = lo * metres, hi * metres
            out.append((lo, hi))
        return tuple(out)

    dofs = {"root": tuple(root["order"])}
    limits = {"root": to_limits(root["order"], None)}
    axis_angles = {"root": np.asarray(root["orientation"], dtype=np.float64)}
    axis_orders = {"root": root["axis"]}
    for name in order[1:]:
        b = bones[name]
        dofs[name] = tuple(b["dof"])
        limits[name] = to_limits(b["dof"], b["limits"])
        axis_angles[name] = np.asarray(b["axis"], dtype=np.float64)
        axis_orders[name] = b["axis_order"]
    axis_rotations = rot.quat_identity(len(order), dtype=torch.float64)
    for axis_order in set(axis_orders.values()):  # one conversion per axis order
        members = [i for i, n in enumerate(order) if axis_orders[n] == axis_order]
        xyz = torch.as_tensor(np.array([axis_angles[order[i]] for i in members]))
        ordered = xyz[:, ["XYZ".index(c) for c in axis_order]]
        axis_rotations[members] = rot.euler_to_quat(axis_order.lower(), ordered, degrees=degrees)
    if not degrees:
        axis_angles = {n: np.degrees(a) for n, a in axis_angles.items()}
    return AsfSkeleton(
        skeleton=skeleton, dofs=dofs, limits=limits, axis_angles=axis_angles, axis_orders=axis_orders,
        axis_rotations=axis_rotations.numpy(), root_order=tuple(root["order"]), root_axis=root["axis"],
        root_position=offsets[0].copy(), units=units, metres_per_unit=metres, directions=directions,
        lengths=lengths, name=_stem(path, ".asf"), path=str(path),
    )


_LIMIT = re.compile(r"\(\s*(\S+)\s+(\S+)\s*\)")


def _parse_limits(path, text: str, line: int) -> list[tuple[float, float]]:
    pairs = _LIMIT.findall(text)
    leftover = _LIMIT.sub("", text).strip()
    if leftover or not pairs:
        raise MotionFileError(path, f"limits should be '(min max)' pairs, got {text.strip()!r}", line=line)
    out = []
    for lo, hi in pairs:
        try:
            a, b = float(lo), float(hi)
        except ValueError:
            raise MotionFileError(path, f"non-numeric limit in ({lo} {hi})", line=line) from None
        if math.isnan(a) or math.isnan(b):
            raise MotionFileError(path, f"NaN limit in ({lo} {hi})", line=line)
        out.append((a, b))
    return out


def _stem(path, suffix: str) -> str:
    name = Path(path).name
    if name.lower().endswith(".gz"):
        name = name[:-3]
    if name.lower().endswith(suffix):
        name = name[: -len(suffix)]
    return name


# ----------------------------------------------------------------------------------------------
# finding the ASF of an AMC
# ----------------------------------------------------------------------------------------------
def _subject_candidates(amc_path: Path) -> list[str]:
    """Stems an ASF for this AMC may have: the name's prefixes at '_' (and '-'), longest first.

    01_01.amc -> 01_01, 01; HDM_bd_squat1Reps_001_120.amc -> ..., HDM_bd, HDM; 07_01-walk -> ..., 07.
    """
    stem = _stem(amc_path, ".amc")
    cuts = [m.start() for m in re.finditer(r"[_\-]", stem)]
    return [stem] + [stem[:c] for c in reversed(cuts) if c > 0]


def _asf_files(folder: Path) -> dict[str, Path]:
    """lower-case stem -> path of every .asf / .asf.gz file in folder."""
    found = {}
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return found
    for p in entries:
        lower = p.name.lower()
        if lower.endswith(".asf") or lower.endswith(".asf.gz"):
            if p.is_file():
                found.setdefault(_stem(p, ".asf").lower(), p)
    return found


def find_asf(amc_path: str | Path) -> Path:
    """The ASF file for an AMC file, by the layouts CMU and HDM05 copies use.

    Looks in the AMC's folder for <subject>.asf (subject = the file name's prefix before '_',
    e.g. 01 for 01_01.amc, HDM_bd for HDM_bd_squat1Reps_001_120.amc) or, failing that, the
    folder's only .asf; then in ../asf/ and ../../asf/ for <subject>.asf. Gzipped .asf.gz and any
    letter case count. Raises MotionFileError saying where it looked.
    """
    amc_path = Path(amc_path)
    folder = amc_path.resolve().parent
    candidates = _subject_candidates(amc_path)
    searched = []
    for i, place in enumerate((folder, folder.parent / "asf", folder.parent.parent / "asf")):
        files = _asf_files(place)
        searched.append(str(place))
        for stem in candidates:
            if stem.lower() in files:
                return files[stem.lower()]
        if i == 0 and len(files) == 1:
            return next(iter(files.values()))
    raise MotionFileError(amc_path, "no ASF skeleton found for this AMC file: looked for "
                          f"{' or '.join(c + '.asf' for c in candidates)} in {', '.join(searched)} "
                          "(and for a single .asf in the AMC's folder); pass asf=PATH")


# ----------------------------------------------------------------------------------------------
# AMC
# ----------------------------------------------------------------------------------------------
_ASF_CACHE: dict[tuple, AsfSkeleton] = {}


def _read_asf_cached(path: Path) -> AsfSkeleton:
    """read_asf, remembered per (file, size, modification time): a folder of AMC files shares one ASF."""
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    except OSError:
        return read_asf(path)  # reports the problem
    if key not in _ASF_CACHE:
        if len(_ASF_CACHE) > 64:
            _ASF_CACHE.clear()
        _ASF_CACHE[key] = read_asf(path)
    return _ASF_CACHE[key]


def _is_frame_number(token: str) -> bool:
    return token.isascii() and token.isdigit()


def read_amc(path: str | Path, asf: str | Path | AsfSkeleton | None = None, fps: float = 120.0,
             allow_truncated: bool = False) -> Motion:
    """Read an Acclaim motion (.amc, optionally gzip-compressed) into a Motion in metres.

    asf: the skeleton, as a path or an AsfSkeleton already read; when None it is found with
        :func:`find_asf` (same folder, ../asf/ or ../../asf/).
    fps: AMC files carry no frame rate; CMU and HDM05 record at 120 Hz.
    allow_truncated: drop an incomplete last frame (a file cut short) instead of raising.
    Every bone with dofs must appear, with one value per dof, in every frame; frame numbers must
    count up by one. Raises MotionFileError naming the file, the 1-based line and the problem
    (and only that, whatever the input).
    """
    path = Path(path)
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise MotionFileError(path, f"fps must be a positive number, got {fps!r}")
    if not isinstance(asf, AsfSkeleton):
        asf = _read_asf_cached(find_asf(path) if asf is None else Path(asf))
    lines = read_text(path).split("\n")
    # Header: comments and :KEYWORDS up to the first frame number.
    degrees = True
    start = None
    for index, raw in enumerate(lines):
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        if text.startswith(":"):
            keyword = text.split()[0].upper()
            if keyword == ":RADIANS":
                degrees = False
            elif keyword == ":DEGREES":
                degrees = True
            continue  # :FULLY-SPECIFIED and others carry nothing we need
        start = index
        break
    if start is None:
        raise MotionFileError(path, "no frames: the file has a header but no frame number / bone lines")
    first = lines[start].split()
    if len(first) != 1 or not _is_frame_number(first[0]):
        raise MotionFileError(path, f"expected a frame number to start the motion data, got {lines[start].strip()[:60]!r}",
                              line=start + 1)

    parsed = _parse_regular(lines, start, asf)
    if parsed is None:
        parsed = _parse_general(path, lines, start, asf, allow_truncated)
    frame_count, values = parsed
    return _to_motion(path, asf, frame_count, values, degrees, fps)


_SAFE_FIRST = frozenset("abcdefghjklmopqrstuvwxyzABCDEFGHJKLMOPQRSTUVWXYZ_")  # not i/n (inf, nan)


def _fast_name(name: str) -> bool:
    """Whether a bone name can never be read as a number (the fast path relies on it)."""
    lower = name.lower()
    return (name[:1].isalpha() or name[:1] == "_") and not any(w.startswith(lower) for w in ("infinity", "nan"))


def _parse_regular(lines: list[str], start: int, asf: AsfSkeleton):
    """Fast path for the usual layout: every frame lists the same bones in the same order.

    Returns (frames, {bone: (F, dofs) float64}) or None when anything is off, in which case the
    line-by-line parser reads the file again and reports the exact line. What it accepts it has
    fully checked: the frame-number lines are where the layout puts them and count up by one;
    every other line starts, unindented, with a token that cannot be a number (its bone name's
    first letter, or the whole name); the whitespace-separated tokens are exactly the layout's,
    names and frame numbers in their places and every other token a finite number. Since each
    line's first token is then the only non-number on it, every line holds its name and exactly
    its bone's values. Blank or comment lines in the data break the layout and go to the slow path.
    """
    body = lines[start:]
    while body and not body[-1].strip():
        body.pop()
    k = 1
    while k < len(body) and not _is_frame_number(body[k].strip()):
        k += 1
    if len(body) % k:
        return None
    n = len(body) // k
    frame_tokens = [s.strip() for s in body[0::k]]
    first = int(frame_tokens[0])
    if frame_tokens != [str(i) for i in range(first, first + n)]:
        return None
    names = []
    for line in body[1:k]:
        head = line.split(None, 1)
        if not head or head[0] not in asf.dofs or not _fast_name(head[0]):
            return None
        names.append(head[0])
    if len(set(names)) != len(names) or any(a != b and b.startswith(a) for a in names for b in names):
        return None
    if any(dofs and b not in names for b, dofs in asf.dofs.items()):
        return None
    text = "\n" + "\n".join(body)
    firsts = [line[:1] for line in body]  # a bone line must start with its name, unindented
    for column, name in enumerate(names, start=1):
        if name[0] in _SAFE_FIRST:  # a token starting so is never a number
            if firsts[column::k].count(name[0]) != n:
                return None
        elif text.count("\n" + name) != n:
            return None
    tokens = text.split()
    width = 1 + sum(1 + len(asf.dofs[name]) for name in names)  # tokens per frame
    if len(tokens) != n * width or tokens[0::width] != frame_tokens:
        return None
    position, value_positions = 1, []
    for name in names:
        if tokens[position::width].count(name) != n:
            return None
        d = len(asf.dofs[name])
        value_positions.extend(range(position + 1, position + 1 + d))
        position += 1 + d
    flat: list[str] = []
    for p in value_positions:
        flat.extend(tokens[p::width])
    try:
        array = np.array(flat, dtype=np.float64).reshape(len(value_positions), n).T
    except (ValueError, OverflowError):
        return None
    if not np.isfinite(array).all():
        return None
    values, column = {}, 0
    for name in names:
        d = len(asf.dofs[name])
        if d:
            values[name] = array[:, column:column + d]
        column += d
    return n, values


def _parse_general(path: Path, lines: list[str], start: int, asf: AsfSkeleton, allow_truncated: bool = False):
    """Line-by-line AMC parser: any bone order per frame, exact errors. Returns like _parse_regular."""
    needed = [b for b in asf.skeleton.names if asf.dofs[b]]
    rows: dict[str, list[list[float]]] = {b: [] for b in needed}
    frame_numbers: list[int] = []
    current: dict[str, int] = {}
    frame_line = None
    last = max(i for i in range(start, len(lines)) if lines[i].strip())  # last line with text

    def incomplete(at_end: bool, line: int):
        missing = [b for b in needed if b not in current]
        where = "truncated last frame" if at_end else "incomplete frame"
        return MotionFileError(path, f"{where}: frame {frame_numbers[-1]} (from line {frame_line}) lacks "
                               f"{len(missing)} bone line(s): {', '.join(missing[:6])}"
                               f"{' ...' if len(missing) > 6 else ''}", line=line)

    def drop_last_frame():
        for b in current:
            if b in rows:
                rows[b].pop()
        frame_numbers.pop()

    for index in range(start, last + 1):
        lineno = index + 1
        text = lines[index].strip()
        if not text or text.startswith("#"):
            continue
        tokens = text.split()
        if _is_frame_number(tokens[0]):
            if len(tokens) != 1:
                raise MotionFileError(path, f"a frame number line should hold only the number, got {text[:60]!r}", line=lineno)
            number = int(tokens[0])
            if frame_numbers:
                if any(b not in current for b in needed):
                    raise incomplete(False, frame_line)
                if number != frame_numbers[-1] + 1:
                    problem = "out of order" if number <= frame_numbers[-1] else "missing"
                    raise MotionFileError(path, f"frame {number} follows frame {frame_numbers[-1]}: frames {problem}", line=lineno)
            frame_numbers.append(number)
            current = {}
            frame_line = lineno
            continue
        if text.startswith(":"):
            raise MotionFileError(path, f"header keyword {tokens[0]!r} inside the motion data", line=lineno)
        name = tokens[0]
        if not frame_numbers:
            raise MotionFileError(path, f"bone line before the first frame number: {text[:60]!r}", line=lineno)
        if name not in asf.dofs:
            raise MotionFileError(path, f"unknown bone {name[:40]!r} (the ASF {asf.name!r} has: "
                                  f"{', '.join(asf.skeleton.names)})", line=lineno)
        if name in current:
            raise MotionFileError(path, f"bone {name!r} appears twice in frame {frame_numbers[-1]} "
                                  f"(first at line {current[name]})", line=lineno)
        dofs = asf.dofs[name]
        cut = index == last  # the file's last line: a cut-off file ends mid-line
        if len(tokens) - 1 != len(dofs):
            if cut and allow_truncated and len(tokens) - 1 < len(dofs):
                break
            raise MotionFileError(path, f"bone {name!r} has {len(tokens) - 1} value(s) but its ASF dofs "
                                  f"({' '.join(dofs) or 'none'}) need {len(dofs)}"
                                  f"{' (the file seems truncated)' if cut else ''}", line=lineno)
        try:
            vals = [float(t) for t in tokens[1:]]
        except ValueError:
            if cut and allow_truncated:
                break
            bad = next(t for t in tokens[1:] if not _is_float(t))
            raise MotionFileError(path, f"non-numeric value {bad[:30]!r} for bone {name!r}", line=lineno) from None
        if not all(math.isfinite(v) for v in vals):
            raise MotionFileError(path, f"NaN or infinite value for bone {name!r}", line=lineno)
        current[name] = lineno
        if dofs:
            rows[name].append(vals)
    if any(b not in current for b in needed):
        if not allow_truncated:
            raise incomplete(True, last + 1)
        drop_last_frame()
        if not frame_numbers:
            raise MotionFileError(path, "no complete frame in the file", line=last + 1)
    n = len(frame_numbers)
    values = {b: np.asarray(r, dtype=np.float64).reshape(n, len(asf.dofs[b])) for b, r in rows.items()}
    return n, values


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _to_motion(path: Path, asf: AsfSkeleton, frames: int, values: dict[str, np.ndarray], degrees: bool,
               fps: float) -> Motion:
    """Turn per-bone dof values into local quaternions, root positions and (if needed) offsets."""
    skeleton = asf.skeleton
    names = skeleton.names
    joints = len(names)
    metres = asf.metres_per_unit
    # Motion rotations M, batched. Rotation dofs in x, y, z order (any subset) all go through one
    # extrinsic "xyz" conversion, absent axes at zero angle; other orders get one call each.
    local = rot.quat_identity(frames, joints, dtype=torch.float64)
    groups: dict[str, list[int]] = {}
    for j, name in enumerate(names):
        axes_used = "".join(d[1] for d in asf.dofs[name] if d in _ROTATION_DOFS)  # "xz": extrinsic
        if axes_used:
            groups.setdefault(axes_used if axes_used not in ("x", "y", "z", "xy", "xz", "yz") else "xyz", []).append(j)
    for convention, members in groups.items():
        angles = np.zeros((frames, len(members), len(convention)))
        for m, j in enumerate(members):
            dofs = asf.dofs[names[j]]
            for i, d in enumerate(dofs):
                if d in _ROTATION_DOFS:
                    angles[:, m, convention.index(d[1])] = values[names[j]][:, i]
        local[:, members] = rot.euler_to_quat(convention, torch.from_numpy(angles), degrees=degrees)
    # Conjugate by each joint's axis rotation C (skipping identities): local = C M C^-1.
    axes_all = torch.as_tensor(asf.axis_rotations, dtype=torch.float64)
    turned = [j for j in range(joints) if asf.dofs[names[j]] and abs(float(axes_all[j, 0])) < 1.0 - 1e-15]
    if turned:
        axes = axes_all[turned].expand(frames, len(turned), 4)
        local[:, turned] = rot.quat_mul(rot.quat_mul(axes, local[:, turned]), rot.quat_inv(axes))

    root_positions = np.repeat(asf.root_position[None], frames, axis=0)
    joint_offsets = None
    for j, name in enumerate(names):
        dofs = asf.dofs[name]
        if not any(d in _TRANSLATION_DOFS or d == "l" for d in dofs):
            continue
        v = values[name]
        t = np.zeros((frames, 3))
        moved = False
        for i, d in enumerate(dofs):
            if d in _TRANSLATION_DOFS:
                t[:, _TRANSLATION_DOFS.index(d)] = v[:, i] * metres
                moved = True
        if j == 0:
            root_positions = root_positions + t
            continue
        if joint_offsets is None:
            joint_offsets = np.repeat(skeleton.offsets[None], frames, axis=0)
        if moved:
            joint_offsets[:, j] += rot.quat_apply(axes_all[j].expand(frames, 4), torch.from_numpy(t)).numpy()
        if "l" in dofs:
            stretch = v[:, dofs.index("l")] * metres
            for child in skeleton.children(j):
                joint_offsets[:, child] += stretch[:, None] * asf.directions[name]
    try:
        return Motion(skeleton=skeleton, rotations=local.float(), root_positions=root_positions,
                      fps=float(fps), joint_offsets=joint_offsets, name=_stem(path, ".amc"))
    except ValueError as error:  # values too large for float32 end up infinite
        raise MotionFileError(path, f"values out of range: {error}") from None
