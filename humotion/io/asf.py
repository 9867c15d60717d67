"""Acclaim ASF skeleton files: read_asf and AsfSkeleton (how ASF maps onto a Skeleton: humotion.io.asf_amc).

read_asf reads in three steps: _AsfParser goes through the sections line by line (:units,
:root, the :bonedata blocks, :hierarchy), _depth_first_order puts the bones in parent-before-
child order, and _assemble builds the Skeleton (metres), the dofs, limits and axis rotations.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, file_stem, read_text
from humotion.skeleton import Skeleton

__all__ = ["AsfSkeleton", "read_asf", "INCH", "ROTATION_DOFS", "TRANSLATION_DOFS"]

INCH = 0.0254  # metres
ROTATION_DOFS = ("rx", "ry", "rz")  # the channels of AsfSkeleton.dofs that rotate a bone,
TRANSLATION_DOFS = ("tx", "ty", "tz")  # that move it, in x, y, z order
_DOFS = ROTATION_DOFS + TRANSLATION_DOFS + ("l",)
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


def read_asf(path: str | Path) -> AsfSkeleton:
    """Read an Acclaim skeleton (.asf, optionally gzip-compressed) into an AsfSkeleton.

    Raises MotionFileError (file, line, problem) for anything it cannot read: missing bonedata
    fields, unknown names or cycles in :hierarchy, bones left out of the hierarchy, malformed
    numbers, dof/limit count mismatches.
    """
    path = Path(path)
    parsed = _AsfParser(path).parse(read_text(path).split("\n"))
    order = _depth_first_order(path, parsed.bones, parsed.children)
    return _assemble(path, parsed, order)


# -- reading the sections --------------------------------------------------------------------

class _AsfParser:
    """The sections of an ASF file, read line by line.

    units: the :units values. root: order, axis, position, orientation. bones: bone name -> its
    bonedata block (fields as read, plus the lines they were on). children / parent_of: the
    :hierarchy, children in file order.
    """

    def __init__(self, path: Path):
        self.path = path
        self.units: dict[str, float | str] = {"length": 1.0, "angle": "deg", "mass": 1.0}
        self.root = {"order": ("tx", "ty", "tz", "rx", "ry", "rz"), "axis": "XYZ", "position": [0.0] * 3,
                     "orientation": [0.0] * 3}
        self.bones: dict[str, dict] = {}
        self.children: dict[str, list[str]] = {}
        self.parent_of: dict[str, str] = {}
        self.section: str | None = None
        self.bone: dict | None = None  # the bonedata block being read
        self.in_hierarchy_block = False
        self.last_key: str | None = None
        self.seen_sections: set[str] = set()

    def error(self, problem: str, line: int | None = None) -> MotionFileError:
        return MotionFileError(self.path, problem, line=line)

    def parse(self, lines: list[str]) -> "_AsfParser":
        for index, raw in enumerate(lines):
            text = raw.strip()
            if text and not text.startswith("#"):
                self._line(index + 1, text)
        if self.bone is not None:
            raise self.error(f"bone block opened at line {self.bone['line']} has no 'end'", len(lines))
        if "bonedata" not in self.seen_sections and "hierarchy" not in self.seen_sections:
            raise self.error("not an ASF file: no :bonedata or :hierarchy section")
        if self.in_hierarchy_block:
            raise self.error(":hierarchy block has no 'end'", len(lines))
        return self

    def _line(self, lineno: int, text: str) -> None:
        tokens = text.split()
        key = tokens[0].lower()
        if text.startswith(":"):
            self._section_line(lineno, tokens, key)
            return
        read = {"units": self._units_line, "root": self._root_line, "bonedata": self._bonedata_line,
                "hierarchy": self._hierarchy_line}.get(self.section)
        if read is not None:
            read(lineno, text, tokens, key)
        elif self.section is None:
            raise self.error(f"text before the first ':section' line: {text!r}", lineno)
        # text in ignored sections (:version, :name, :documentation, unknown) is skipped

    def _section_line(self, lineno: int, tokens: list[str], key: str) -> None:
        if self.bone is not None:
            raise self.error(f"bone block opened at line {self.bone['line']} has no 'end'", lineno)
        self.section = key[1:]
        self.seen_sections.add(self.section)
        self.last_key = None
        if self.section in ("units", "root", "bonedata", "hierarchy") and len(tokens) > 1:
            raise self.error(f"unexpected text after {tokens[0]}", lineno)
        # :version, :name, :documentation and unknown sections carry nothing we use

    def _units_line(self, lineno: int, text: str, tokens: list[str], key: str) -> None:
        if len(tokens) != 2:
            raise self.error(f"units line should be 'name value', got {text!r}", lineno)
        if key == "angle":
            unit = tokens[1].lower()
            if unit not in ("deg", "rad"):
                raise self.error(f"angle unit {tokens[1]!r} is neither 'deg' nor 'rad'", lineno)
            self.units["angle"] = unit
        else:
            value = _floats(self.path, tokens[1:], lineno, f"units {key}", 1)[0]
            if key == "length" and not value > 0:
                raise self.error(f"length unit must be positive, got {value}", lineno)
            self.units[key] = value

    def _root_line(self, lineno: int, text: str, tokens: list[str], key: str) -> None:
        if key == "order":
            order = tuple(t.lower() for t in tokens[1:])
            _check_dofs(self.path, order, lineno, "root order")
            if any(d == "l" for d in order):
                raise self.error("root order cannot contain 'l'", lineno)
            self.root["order"] = order
        elif key == "axis":
            if len(tokens) != 2:
                raise self.error(f"root axis should be one order like XYZ, got {text!r}", lineno)
            self.root["axis"] = _axis_order(self.path, tokens[1], lineno)
        elif key in ("position", "orientation"):
            self.root[key] = _floats(self.path, tokens[1:], lineno, f"root {key}", 3)
        else:
            raise self.error(f"unknown root field {tokens[0]!r}", lineno)

    def _bonedata_line(self, lineno: int, text: str, tokens: list[str], key: str) -> None:
        bone = self.bone
        if key == "begin":
            if bone is not None:
                raise self.error(f"'begin' inside the bone block opened at line {bone['line']}", lineno)
            self.bone = {"line": lineno, "dof": (), "limits": None}
            self.last_key = None
        elif bone is None:
            raise self.error(f"bonedata field {tokens[0]!r} outside a begin/end block", lineno)
        elif key == "end":
            self._close_bone(bone)
        elif text.startswith("(") and self.last_key == "limits":  # limits continued on this line
            bone["limits_text"] += " " + text
            bone["limits"] = _parse_limits(self.path, bone["limits_text"], lineno)
        else:
            self.last_key = key
            self._bone_field(bone, lineno, text, tokens, key)

    def _bone_field(self, bone: dict, lineno: int, text: str, tokens: list[str], key: str) -> None:
        if key in ("id", "bodymass", "cofmass"):
            return
        if key == "name":
            if len(tokens) != 2:
                raise self.error(f"bone name should be one word, got {text!r}", lineno)
            bone["name"], bone["name_line"] = tokens[1], lineno
        elif key == "direction":
            bone["direction"] = _floats(self.path, tokens[1:], lineno, "direction", 3)
        elif key == "length":
            bone["length"] = _floats(self.path, tokens[1:], lineno, "length", 1)[0]
        elif key == "axis":
            if len(tokens) != 5:
                raise self.error(f"axis should be 'axis ax ay az ORDER', got {text!r}", lineno)
            bone["axis"] = _floats(self.path, tokens[1:4], lineno, "axis", 3)
            bone["axis_order"] = _axis_order(self.path, tokens[4], lineno)
        elif key == "dof":
            bone["dof"] = _check_dofs(self.path, tokens[1:], lineno, "dof")
        elif key == "limits":
            bone["limits_text"], bone["limits_line"] = text[len(tokens[0]):], lineno
            bone["limits"] = _parse_limits(self.path, bone["limits_text"], lineno)
        else:
            raise self.error(f"unknown bonedata field {tokens[0]!r}", lineno)

    def _close_bone(self, bone: dict) -> None:
        missing = [f for f in _BONE_FIELDS if f not in bone]
        if missing:
            raise self.error(f"bone block has no {', '.join(missing)}", bone["line"])
        if bone["limits"] is not None and len(bone["limits"]) != len(bone["dof"]):
            raise self.error(f"bone {bone['name']!r} has {len(bone['dof'])} dofs but "
                             f"{len(bone['limits'])} limits", bone["limits_line"])
        if bone["name"] in self.bones or bone["name"] == "root":
            problem = "is reserved for the root" if bone["name"] == "root" else "is used twice"
            raise self.error(f"bone name {bone['name']!r} {problem}", bone["name_line"])
        self.bones[bone["name"]] = bone
        self.bone = None

    def _hierarchy_line(self, lineno: int, text: str, tokens: list[str], key: str) -> None:
        if key in ("begin", "end"):
            self.in_hierarchy_block = key == "begin"
            return
        if not self.in_hierarchy_block:
            raise self.error(f"hierarchy line outside begin/end: {text!r}", lineno)
        parent = tokens[0]
        if parent != "root" and parent not in self.bones:
            raise self.error(f"unknown parent {parent!r} in :hierarchy (not a bone in :bonedata)", lineno)
        if len(tokens) < 2:
            raise self.error(f"hierarchy line names parent {parent!r} but no children", lineno)
        for child in tokens[1:]:
            if child not in self.bones:
                raise self.error(f"unknown child {child!r} in :hierarchy (not a bone in :bonedata)", lineno)
            if child in self.parent_of:
                raise self.error(f"bone {child!r} is given a second parent ({parent!r}, "
                                 f"already under {self.parent_of[child]!r})", lineno)
            self.parent_of[child] = parent
            self.children.setdefault(parent, []).append(child)


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


# -- building the skeleton -------------------------------------------------------------------

def _depth_first_order(path: Path, bones: dict[str, dict], children: dict[str, list[str]]) -> list[str]:
    """"root", then the bones depth-first, children in file order: parents before children."""
    order: list[str] = ["root"]
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
    return order


def _assemble(path: Path, parsed: _AsfParser, order: list[str]) -> AsfSkeleton:
    """The AsfSkeleton of a parsed file, joints in `order`."""
    units, root, bones = parsed.units, parsed.root, parsed.bones
    metres = INCH / float(units["length"])
    degrees = units["angle"] == "deg"
    skeleton, offsets, directions, lengths = _skeleton(path, parsed, order, metres)
    dofs = {"root": tuple(root["order"])}
    limits = {"root": _limits(root["order"], None, metres, degrees)}
    axis_angles = {"root": np.asarray(root["orientation"], dtype=np.float64)}
    axis_orders = {"root": root["axis"]}
    for name in order[1:]:
        b = bones[name]
        dofs[name] = tuple(b["dof"])
        limits[name] = _limits(b["dof"], b["limits"], metres, degrees)
        axis_angles[name] = np.asarray(b["axis"], dtype=np.float64)
        axis_orders[name] = b["axis_order"]
    axis_rotations = _axis_rotations(order, axis_angles, axis_orders, degrees)
    if not degrees:
        axis_angles = {n: np.degrees(a) for n, a in axis_angles.items()}
    return AsfSkeleton(
        skeleton=skeleton, dofs=dofs, limits=limits, axis_angles=axis_angles, axis_orders=axis_orders,
        axis_rotations=axis_rotations.numpy(), root_order=tuple(root["order"]), root_axis=root["axis"],
        root_position=offsets[0].copy(), units=units, metres_per_unit=metres, directions=directions,
        lengths=lengths, name=file_stem(path, ".asf"), path=str(path),
    )


def _skeleton(path: Path, parsed: _AsfParser, order: list[str], metres: float):
    """(Skeleton, (J, 3) joint offsets, bone directions, bone lengths in metres): each joint at its
    bone's start, i.e. its parent bone's direction * length from the parent joint; end sites at
    the ends of leaf bones."""
    bones, parent_of, children = parsed.bones, parsed.parent_of, parsed.children
    index = {n: i for i, n in enumerate(order)}
    offsets = np.zeros((len(order), 3))
    offsets[0] = np.asarray(parsed.root["position"]) * metres
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
    return skeleton, offsets, directions, lengths


def _limits(dofs, lims, metres: float, degrees: bool) -> tuple[tuple[float, float], ...]:
    """One (min, max) per dof: degrees for rotations, metres otherwise; unbounded without limits."""
    if lims is None:
        return tuple((-math.inf, math.inf) for _ in dofs)
    out = []
    for d, (lo, hi) in zip(dofs, lims):
        if d in ROTATION_DOFS:
            lo, hi = (lo, hi) if degrees else (math.degrees(lo), math.degrees(hi))
        else:
            lo, hi = lo * metres, hi * metres
        out.append((lo, hi))
    return tuple(out)


def _axis_rotations(order: list[str], axis_angles: dict[str, np.ndarray], axis_orders: dict[str, str],
                    degrees: bool) -> torch.Tensor:
    """(J, 4) float64 quaternion C of every joint's axis, one conversion per axis order."""
    axis_rotations = rot.quat_identity(len(order), dtype=torch.float64)
    for axis_order in set(axis_orders.values()):
        members = [i for i, n in enumerate(order) if axis_orders[n] == axis_order]
        xyz = torch.as_tensor(np.array([axis_angles[order[i]] for i in members]))
        ordered = xyz[:, ["XYZ".index(c) for c in axis_order]]
        axis_rotations[members] = rot.euler_to_quat(axis_order.lower(), ordered, degrees=degrees)
    return axis_rotations
