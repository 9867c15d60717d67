"""Recorded headset streams: the files ``humotion track RECORDING`` reads.

A recording holds, per headset frame, the time, the headset pose and each hand's pose when the
hand is tracked. Two containers carry the same fields: CSV (a header line, then one row per frame)
and JSON; the suffix picks (.csv, .json, either optionally .gz).

Fields (column names exactly as written, any order; unknown columns are ignored):

==========================================  ====================================================
timestamp                                   seconds, strictly increasing
head_px, head_py, head_pz                   headset position, metres: the point between the eyes
                                            (OpenXR VIEW space / the camera), not the neck
head_qw, head_qx, head_qy, head_qz          headset orientation, unit quaternion, SCALAR FIRST
left_visible                                1 when the left hand is tracked on this frame, else 0
                                            (true / false accepted)
left_px, left_py, left_pz                   left WRIST position, metres
left_qw, left_qx, left_qy, left_qz          left wrist orientation (see hand_frame below)
right_visible, right_px, ... right_qz       the same for the right hand
==========================================  ====================================================

The head fields are required on every frame. A hand's eight columns are all present or all absent
(absent: that hand is never tracked). When a hand is not visible its pose cells may be empty or
``nan`` (or hold a stale pose, which is ignored). A hand flagged visible whose seven pose cells
are all empty (or nan) is read as hidden on that row, and a warning (logger "humotion.sparse")
names the file and the rows, once per file and hand; a partly empty pose is refused. Quaternions
are normalised on reading. Each field appears once: a field's name repeated in the CSV header, or
a key repeated within a JSON object, is refused (which copy would hold the value?).

CSV example (OpenXR axes: the user stands at the origin looking along -Z, left hand in view)::

    timestamp,head_px,head_py,head_pz,head_qw,head_qx,head_qy,head_qz,left_visible,left_px,left_py,left_pz,left_qw,left_qx,left_qy,left_qz,right_visible,right_px,right_py,right_pz,right_qw,right_qx,right_qy,right_qz
    0.0,0,1.6,0,1,0,0,0,1,-0.3,1.2,-0.4,1,0,0,0,0,,,,,,,

JSON: ``{"convention": "openxr", "hand_frame": "tpose", "frames": [{"timestamp": 0.0, "head_px": 0,
..., "left_visible": true, "left_px": -0.3, ...}, ...]}`` -- one object per frame with the CSV
column names as keys; a missing key or null is an empty cell. "convention" and "hand_frame" are
optional; when given they must agree with the reader's arguments (and are used when those are
left out).

Axes (the ``convention`` argument; everything is converted into humotion's frame on reading):

- "openxr": right-handed, Y up, X right, the identity orientation looks along -Z (OpenXR,
  WebXR, OpenGL). To humotion: (x, y, z) -> (-x, y, -z), a half turn about Y.
- "unity": left-handed, Y up, X right, +Z forward (Unity). To humotion: (x, y, z) -> (-x, y, z).
- "humotion": right-handed, Y up, the user faces +Z, so the left is +X.

Orientations are converted by the same change of axes (R -> C R C^T), so an identity head looks
forward in every convention, and a head turned 90 degrees to the left stays turned to the left.

``hand_frame`` says what a hand's identity orientation means (in the file's own axes):
"tpose" (default): the hand of a T-pose, the arm out to the side, fingers pointing away from the
body, palm down -- humotion's canonical wrist frame; "forward": the hand pointing forward, palm
down (OpenXR's XR_EXT_hand_tracking wrist joint: -Z towards the fingers, +Y out of the back of
the hand).

Errors: a malformed file raises :class:`humotion.io.errors.MotionFileError` (a ValueError)
naming the file, the line (CSV) or frame (JSON) and the problem.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, base_suffix, read_text
from humotion.motion import Motion
from humotion.sparse import signals as sg

log = logging.getLogger("humotion.sparse")

CONVENTIONS = {
    "openxr": np.diag([-1.0, 1.0, -1.0]),
    "unity": np.diag([-1.0, 1.0, 1.0]),
    "humotion": np.eye(3),
}
HAND_FRAMES = ("tpose", "forward")
HEAD_COLUMNS = ("head_px", "head_py", "head_pz", "head_qw", "head_qx", "head_qy", "head_qz")


def hand_columns(side: str) -> tuple[str, ...]:
    """The eight column names of one hand ('left' or 'right')."""
    return (f"{side}_visible",) + tuple(f"{side}_{c}" for c in ("px", "py", "pz", "qw", "qx", "qy", "qz"))


COLUMNS = ("timestamp",) + HEAD_COLUMNS + hand_columns("left") + hand_columns("right")


@dataclass(frozen=True)
class HeadsetFrame:
    """One headset frame in humotion's axes, as SparseTracker.update takes it (humotion.live's
    protocol decodes its messages into it).

    timestamp: seconds, increasing along a stream. head, left, right: (rotation (3, 3),
    position (3,) metres) of the eyes and of each wrist (canonical wrist frame), numpy arrays,
    tensors or lists; a hand is None when it is not tracked on this frame.
    """

    timestamp: float
    head: tuple
    left: tuple | None = None
    right: tuple | None = None


@dataclass(eq=False)
class HeadsetStream:
    """A headset recording in humotion's frame (metres, seconds, Y up, user faces +Z, left +X).

    timestamps: (T,) seconds; head_rotations (T, 3, 3) / head_positions (T, 3): the eyes;
    left_* / right_*: the wrists (canonical wrist frame), NaN where not known;
    visible: (T, 2) bool, left and right. Tensors are float64 (visible bool).
    """

    timestamps: torch.Tensor
    head_rotations: torch.Tensor
    head_positions: torch.Tensor
    left_rotations: torch.Tensor
    left_positions: torch.Tensor
    right_rotations: torch.Tensor
    right_positions: torch.Tensor
    visible: torch.Tensor

    def __post_init__(self):
        for name in ("timestamps", "head_rotations", "head_positions", "left_rotations", "left_positions",
                     "right_rotations", "right_positions"):
            setattr(self, name, torch.as_tensor(getattr(self, name), dtype=torch.float64))
        self.visible = torch.as_tensor(self.visible, dtype=torch.bool)
        t = self.timestamps.shape[0]
        expected = {"timestamps": (t,), "visible": (t, 2)}
        for device in sg.DEVICES:
            expected[f"{device}_rotations"], expected[f"{device}_positions"] = (t, 3, 3), (t, 3)
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"HeadsetStream.{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")

    def __len__(self) -> int:
        return self.timestamps.shape[0]

    @property
    def fps(self) -> float:
        """Frame rate from the median time step."""
        return 1.0 / float(self.timestamps.diff().median()) if len(self) > 1 else 0.0

    @property
    def rotations(self) -> torch.Tensor:
        """(T, 3, 3, 3) rotations of head, left, right (signals.DEVICES order)."""
        return torch.stack([self.head_rotations, self.left_rotations, self.right_rotations], dim=1)

    @property
    def positions(self) -> torch.Tensor:
        """(T, 3, 3) positions of head, left, right, metres."""
        return torch.stack([self.head_positions, self.left_positions, self.right_positions], dim=1)

    def frame(self, t: int) -> HeadsetFrame:
        """Frame t as a HeadsetFrame (float64 tensor views; a hand None where not visible)."""
        def device(name: str, seen: bool = True) -> tuple | None:
            return (getattr(self, f"{name}_rotations")[t], getattr(self, f"{name}_positions")[t]) if seen else None
        left, right = self.visible[t].tolist()
        return HeadsetFrame(float(self.timestamps[t]), device("head"), device("left", left), device("right", right))

    def frames(self) -> Iterator[HeadsetFrame]:
        """Every frame in order (:meth:`frame`): a recording replayed as a live stream."""
        return map(self.frame, range(len(self)))

    def signals(self, dtype=torch.float32) -> dict:
        """Model input signals (signals.pose_signals), unseen hands hidden (signals.hide_unseen)."""
        return sg.hide_unseen(sg.pose_signals(self.rotations.to(dtype), self.positions.to(dtype), self.visible))


def stream_from_motion(motion: Motion, scenario: str = "MC", frustum: sg.Frustum = sg.Frustum(),
                       dropout: sg.Dropout | None = None, generator: torch.Generator | None = None,
                       keep_hidden: bool = False) -> HeadsetStream:
    """What a headset would record from a motion (canonical body; other rigs are mapped).

    Head at the eyes, hands at the wrists, visibility per scenario ('MC' or 'HT', signals module).
    keep_hidden: keep the true pose of unseen hands instead of NaN. Timestamps start at 0.
    """
    if motion.skeleton.names != sg.canonical.JOINTS:
        motion = sg.canonical.to_canonical(motion)
    r, p = sg.device_poses(*motion.world(), sg.eye_offset(motion.skeleton))
    visible = sg.simulate_visibility(r, p, scenario, frustum, dropout, motion.fps, generator)
    r, p = r.double(), p.double()
    if not keep_hidden:
        hidden = torch.cat([torch.zeros_like(visible[:, :1]), ~visible], dim=1)
        r, p = r.masked_fill(hidden[..., None, None], math.nan), p.masked_fill(hidden[..., None], math.nan)
    times = torch.arange(motion.num_frames, dtype=torch.float64) / motion.fps
    return HeadsetStream(times, r[:, 0], p[:, 0], r[:, 1], p[:, 1], r[:, 2], p[:, 2], visible)


# -- axes ---------------------------------------------------------------------------------------
def _check(convention: str, hand_frame: str) -> None:
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; expected one of {', '.join(CONVENTIONS)}")
    if hand_frame not in HAND_FRAMES:
        raise ValueError(f"unknown hand_frame {hand_frame!r}; expected one of {', '.join(HAND_FRAMES)}")


def hand_offset(side: str, hand_frame: str) -> torch.Tensor:
    """The (3, 3) float64 rotation taking a hand_frame ("tpose" or "forward") orientation of the
    side ("left" or "right") hand to the canonical wrist frame (right-multiplied)."""
    if hand_frame == "tpose":
        return torch.eye(3, dtype=torch.float64)
    # Forward hand -> T-pose wrist: the canonical left wrist's fingers (+X) point forward (+Z).
    angle = -90.0 if side == "left" else 90.0
    return rot.quat_to_matrix(rot.euler_to_quat("Y", torch.tensor([angle], dtype=torch.float64)))


def _to_humotion(q_wxyz: torch.Tensor, p: torch.Tensor, convention: str, offset: torch.Tensor):
    c = torch.as_tensor(CONVENTIONS[convention])
    return c @ rot.quat_to_matrix(q_wxyz) @ c.T @ offset, p @ c.T


def from_humotion(r: torch.Tensor, p: torch.Tensor, convention: str, offset: torch.Tensor):
    """Device poses in humotion's frame written in a convention's axes (a key of CONVENTIONS):
    r (N, 3, 3) rotation matrices and p (N, 3) positions, metres -> (wxyz quaternions (N, 4),
    positions (N, 3)). offset (3, 3): hand_offset(side, hand_frame) for a hand, the identity for
    the head. The inverse of what reading a recording does."""
    c = torch.as_tensor(CONVENTIONS[convention])
    return rot.matrix_to_quat(c.T @ r @ offset.T @ c), p @ c


# -- reading ------------------------------------------------------------------------------------
class _JsonObject(dict):
    """A JSON object that keeps the keys it was given more than once (json.loads keeps the last)."""

    def __init__(self, pairs: list[tuple]):
        super().__init__(pairs)
        self.repeated = [k for i, (k, _) in enumerate(pairs) if k in dict(pairs[:i])] if len(self) < len(pairs) else []


def _read_table(path: Path, text: str, fmt: str) -> tuple[list[str], list[list], list[str], dict]:
    """(columns, rows of cells, location label per row, JSON header) from CSV or JSON text."""
    if fmt == ".json":
        try:
            data = json.loads(text, object_pairs_hook=_JsonObject)
        except json.JSONDecodeError as error:
            raise MotionFileError(path, f"invalid JSON ({error.msg})", error.lineno) from None
        if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
            raise MotionFileError(path, 'expected a JSON object with a "frames" list of frame objects')
        if data.repeated:
            raise MotionFileError(path, f'key "{data.repeated[0]}" appears more than once in the top-level object')
        frames = data["frames"]
        for i, frame in enumerate(frames):
            if not isinstance(frame, dict):
                raise MotionFileError(path, f"frame {i}: expected an object of column: value, got {type(frame).__name__}")
            if frame.repeated:
                raise MotionFileError(path, f'frame {i}: key "{frame.repeated[0]}" appears more than once')
        columns = list(dict.fromkeys(k for frame in frames for k in frame))
        rows = [[frame.get(c) for c in columns] for frame in frames]
        return columns, rows, [f"frame {i}" for i in range(len(frames))], data
    reader = csv.reader(io.StringIO(text))
    rows, where, columns = [], [], None
    for cells in reader:
        if not any(cell.strip() for cell in cells):
            continue
        if columns is None:
            columns = [cell.strip() for cell in cells]
            _refuse_repeated_columns(path, columns, reader.line_num)
            continue
        if len(cells) != len(columns):
            raise MotionFileError(path, f"{len(cells)} fields, the header has {len(columns)}", reader.line_num)
        rows.append(cells)
        where.append(f"line {reader.line_num}")
    return columns or [], rows, where, {}


def _refuse_repeated_columns(path: Path, columns: list[str], line: int) -> None:
    """A header naming a recording column twice is ambiguous (which copy holds the value?)."""
    for name in COLUMNS:
        fields = [i + 1 for i, c in enumerate(columns) if c == name]
        if len(fields) > 1:
            raise MotionFileError(path, f'column "{name}" appears more than once in the header '
                                        f'(fields {", ".join(map(str, fields))})', line)


def _number(cell, column: str, path: Path, where: str) -> float:
    if cell is None or (isinstance(cell, str) and not cell.strip()):
        return math.nan
    if isinstance(cell, bool) or not isinstance(cell, (int, float, str)):
        raise MotionFileError(path, f"{where}: {column} is {cell!r}, not a number")
    try:
        return float(cell)
    except ValueError:
        raise MotionFileError(path, f"{where}: {column} is {cell!r}, not a number") from None


def _flag(cell, column: str, path: Path, where: str) -> bool:
    text = str(cell).strip().lower()
    if text in ("1", "1.0", "true"):
        return True
    if text in ("0", "0.0", "false"):
        return False
    raise MotionFileError(path, f"{where}: {column} is {cell!r}; expected 1 or 0 (true or false)")


def _poses(values: np.ndarray, path: Path, where: list[str], label: str, required: np.ndarray):
    """(quaternions (T, 4), positions (T, 3)) from 7 columns p, q; checks rows where required."""
    bad = required & ~np.isfinite(values).all(1)
    if bad.any():
        i = int(np.argmax(bad))
        raise MotionFileError(path, f"{where[i]}: {label} pose is missing or not a number" +
                              (" (the hand is marked visible)" if label != "head" else ""))
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.linalg.norm(values[:, 3:], axis=1)
        unit = values[:, 3:] / norm[:, None]
    bad = required & ((norm < 0.9) | (norm > 1.1))
    if bad.any():
        i = int(np.argmax(bad))
        raise MotionFileError(path, f"{where[i]}: {label} quaternion has norm {norm[i]:.3g}, not a unit quaternion")
    return torch.as_tensor(unit), torch.as_tensor(values[:, :3])


def _unposed(values: np.ndarray, seen: np.ndarray, path: Path, where: list[str], side: str) -> np.ndarray:
    """(T,) rows where the hand is flagged visible but all seven pose cells are empty; a warning
    names them (a partly empty pose is refused later, by _poses)."""
    unposed = seen & np.isnan(values).all(1)
    rows = [where[i] for i in np.flatnonzero(unposed)]
    if rows:
        log.warning("%s: the %s hand is flagged visible but has no pose at %s%s (%d in all); read as hidden there",
                    path, side, ", ".join(rows[:3]), ", ..." if len(rows) > 3 else "", len(rows))
    return unposed


def read_recording(path: str | Path, convention: str | None = None, hand_frame: str | None = None) -> HeadsetStream:
    """Read a CSV or JSON headset recording (module docstring) into humotion's frame.

    convention: 'openxr', 'unity' or 'humotion' (default: the JSON file's, else 'openxr');
    hand_frame: 'tpose' or 'forward' (default: the JSON file's, else 'tpose').
    Raises MotionFileError naming the file, line / frame and problem.
    """
    path = Path(path)
    _check(convention or "openxr", hand_frame or "tpose")
    fmt = base_suffix(path)
    if fmt not in (".csv", ".json"):
        raise MotionFileError(path, f"unknown recording format {fmt!r}; expected .csv or .json (optionally .gz)")
    columns, rows, where, header = _read_table(path, read_text(path), fmt)
    for key, given, known in (("convention", convention, tuple(CONVENTIONS)), ("hand_frame", hand_frame, HAND_FRAMES)):
        declared = header.get(key)
        if declared is not None and declared not in known:
            raise MotionFileError(path, f"the file declares an unknown {key} {json.dumps(declared)}; "
                                        f"expected one of {', '.join(known)}")
        if declared is not None and given is not None and declared != given:
            raise MotionFileError(path, f'the file declares {key} "{declared}" but {key}={given!r} was asked')
    convention = convention or header.get("convention") or "openxr"
    hand_frame = hand_frame or header.get("hand_frame") or "tpose"
    if not rows:
        raise MotionFileError(path, "no frames")
    missing = [c for c in ("timestamp",) + HEAD_COLUMNS if c not in columns]
    for side in ("left", "right"):
        present = [c for c in hand_columns(side) if c in columns]
        if present and len(present) < 8:
            missing += [c for c in hand_columns(side) if c not in columns]
    if missing:
        raise MotionFileError(path, f"missing columns: {', '.join(missing)} (see humotion.sparse.recording for the format)")

    index = {c: i for i, c in enumerate(columns)}
    def table(names):
        return np.array([[_number(row[index[c]], c, path, where[r]) for c in names] for r, row in enumerate(rows)])

    times = table(["timestamp"])[:, 0]
    step = np.diff(times)
    bad = ~np.isfinite(times) | np.concatenate([[False], ~(step > 0)])
    if bad.any():
        i = int(np.argmax(bad))
        problem = (f"timestamp {float(times[i])!r} is not a number" if not np.isfinite(times[i]) else
                   f"timestamp {float(times[i])!r} is not greater than the one before it ({float(times[i - 1])!r})")
        raise MotionFileError(path, f"{where[i]}: {problem}")
    ones = np.ones(len(rows), dtype=bool)
    q, p = _poses(table(HEAD_COLUMNS), path, where, "head", ones)
    head_r, head_p = _to_humotion(q, p, convention, torch.eye(3, dtype=torch.float64))
    hands, visible = [], []
    for side in ("left", "right"):
        names = hand_columns(side)
        if names[0] not in index:
            seen = np.zeros(len(rows), dtype=bool)
            values = np.full((len(rows), 7), np.nan)
        else:
            seen = np.array([_flag(row[index[names[0]]], names[0], path, where[r]) for r, row in enumerate(rows)])
            values = table(names[1:])
            seen &= ~_unposed(values, seen, path, where, side)
        q, p = _poses(values, path, where, f"{side} hand", seen)
        hands += list(_to_humotion(q, p, convention, hand_offset(side, hand_frame)))
        visible.append(torch.as_tensor(seen))
    return HeadsetStream(torch.as_tensor(times), head_r, head_p, *hands, torch.stack(visible, dim=1))


# -- writing ------------------------------------------------------------------------------------
def write_recording(stream: HeadsetStream, path: str | Path, convention: str = "openxr", hand_frame: str = "tpose") -> None:
    """Write a stream as CSV or JSON (by suffix, .csv or .json), in the given convention's axes.

    Unknown poses (NaN, e.g. unseen hands) are written as empty cells (CSV) or null (JSON).
    """
    path = Path(path)
    _check(convention, hand_frame)
    fmt = path.suffix.lower()
    if fmt not in (".csv", ".json"):
        raise ValueError(f"{path}: write a recording as .csv or .json, not {fmt!r}")
    blocks = [stream.timestamps[:, None]]
    for k, side, r, p in ((-1, "head", stream.head_rotations, stream.head_positions),
                          (0, "left", stream.left_rotations, stream.left_positions),
                          (1, "right", stream.right_rotations, stream.right_positions)):
        if k >= 0:
            blocks.append(stream.visible[:, k:k + 1].double())
        offset = torch.eye(3, dtype=torch.float64) if side == "head" else hand_offset(side, hand_frame)
        known = torch.isfinite(r).all(-1).all(-1) & torch.isfinite(p).all(-1)
        q, pf = from_humotion(torch.where(known[:, None, None], r, torch.eye(3, dtype=r.dtype)), p, convention, offset)
        blocks.append(torch.where(known[:, None], torch.cat([pf, q], dim=1), math.nan))
    values = torch.cat(blocks, dim=1).tolist()
    flags = {COLUMNS.index("left_visible"), COLUMNS.index("right_visible")}

    if fmt == ".json":
        frames = [{c: bool(v) if j in flags else None if math.isnan(v) else v for j, (c, v) in enumerate(zip(COLUMNS, row))}
                  for row in values]
        head = json.dumps({"convention": convention, "hand_frame": hand_frame})[:-1]
        path.write_text(head + ', "frames": [\n' + ",\n".join(json.dumps(f) for f in frames) + "\n]}\n")
        return
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        writer.writerows([[str(int(v)) if j in flags else "" if math.isnan(v) else repr(v) for j, v in enumerate(row)]
                          for row in values])
