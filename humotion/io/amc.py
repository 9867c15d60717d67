"""Acclaim AMC motion files: read_amc, and find_asf for the skeleton file that goes with one.

How AMC channels become a Motion (rotations conjugated by each bone's axis, translations, "l"
stretches): see humotion.io.asf_amc. read_amc reads the header, then the frames with a fast
path for the usual layout (_parse_regular) or line by line with exact errors (_parse_general),
and _to_motion turns the per-bone values into quaternions, root positions and joint offsets.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.io.asf import ROTATION_DOFS, TRANSLATION_DOFS, AsfSkeleton, read_asf
from humotion.io.errors import MotionFileError, file_stem, read_text
from humotion.motion import Motion

__all__ = ["read_amc", "find_asf"]


# -- finding the ASF of an AMC ---------------------------------------------------------------

def _subject_candidates(amc_path: Path) -> list[str]:
    """Stems an ASF for this AMC may have: the name's prefixes at '_' (and '-'), longest first.

    01_01.amc -> 01_01, 01; HDM_bd_squat1Reps_001_120.amc -> ..., HDM_bd, HDM; 07_01-walk -> ..., 07.
    """
    stem = file_stem(amc_path, ".amc")
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
                found.setdefault(file_stem(p, ".asf").lower(), p)
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


# -- AMC ---------------------------------------------------------------------------------------

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
    degrees, start = _read_header(path, lines)
    parsed = _parse_regular(lines, start, asf)
    if parsed is None:
        parsed = _parse_general(path, lines, start, asf, allow_truncated)
    frame_count, values = parsed
    return _to_motion(path, asf, frame_count, values, degrees, fps)


def _read_header(path: Path, lines: list[str]) -> tuple[bool, int]:
    """(angles in degrees, index of the first frame-number line) from the comments and :KEYWORDS
    before the first frame."""
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
    return degrees, start


_SAFE_FIRST = frozenset("abcdefghjklmopqrstuvwxyzABCDEFGHJKLMOPQRSTUVWXYZ_")  # not i/n (inf, nan)


def _fast_name(name: str) -> bool:
    """Whether a bone name can never be read as a number (the fast path relies on it)."""
    lower = name.lower()
    return (name[:1].isalpha() or name[:1] == "_") and not any(w.startswith(lower) for w in ("infinity", "nan"))


def _parse_regular(lines: list[str], start: int, asf: AsfSkeleton):
    """Fast path for the usual layout: every frame lists the same bones in the same order.

    Returns (frames, {bone: (T, dofs) float64}) or None when anything is off, in which case the
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
    layout = _regular_layout(body, asf)
    if layout is None:
        return None
    k, n, frame_tokens, names = layout
    text = "\n" + "\n".join(body)
    firsts = [line[:1] for line in body]  # a bone line must start with its name, unindented
    for column, name in enumerate(names, start=1):
        if name[0] in _SAFE_FIRST:  # a token starting so is never a number
            if firsts[column::k].count(name[0]) != n:
                return None
        elif text.count("\n" + name) != n:
            return None
    array = _regular_values(text.split(), n, frame_tokens, names, asf)
    if array is None:
        return None
    values, column = {}, 0
    for name in names:
        d = len(asf.dofs[name])
        if d:
            values[name] = array[:, column:column + d]
        column += d
    return n, values


def _regular_layout(body: list[str], asf: AsfSkeleton):
    """(lines per frame k, frames n, frame-number tokens, bone names of a frame) when the frame
    numbers sit every k lines and count up by one and the first frame names each bone with dofs
    once (names that are not prefixes of one another and cannot be numbers); else None."""
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
    return k, n, frame_tokens, names


def _regular_values(tokens: list[str], n: int, frame_tokens: list[str], names: list[str], asf: AsfSkeleton):
    """(n, values per frame) float64 array of every bone's values in `names` order, when the tokens
    are exactly the layout's (frame numbers and names in their places, finite numbers between);
    else None."""
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
    return array


def _parse_general(path: Path, lines: list[str], start: int, asf: AsfSkeleton, allow_truncated: bool = False):
    """Line-by-line AMC parser: any bone order per frame, exact errors. Returns like _parse_regular."""
    needed = [b for b in asf.skeleton.names if asf.dofs[b]]
    rows: dict[str, list[list[float]]] = {b: [] for b in needed}
    frame_numbers: list[int] = []
    current: dict[str, int] = {}  # bone -> its line in the current frame
    frame_line = None
    last = max(i for i in range(start, len(lines)) if lines[i].strip())  # last line with text

    def incomplete(at_end: bool, line: int):
        missing = [b for b in needed if b not in current]
        where = "truncated last frame" if at_end else "incomplete frame"
        return MotionFileError(path, f"{where}: frame {frame_numbers[-1]} (from line {frame_line}) lacks "
                               f"{len(missing)} bone line(s): {', '.join(missing[:6])}"
                               f"{' ...' if len(missing) > 6 else ''}", line=line)

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
        _check_bone_line(path, tokens, text, lineno, asf, frame_numbers, current)
        vals = _bone_values(path, tokens, lineno, asf, cut=index == last, allow_truncated=allow_truncated)
        if vals is None:  # the cut-off last line of a truncated file
            break
        current[tokens[0]] = lineno
        if asf.dofs[tokens[0]]:
            rows[tokens[0]].append(vals)
    if any(b not in current for b in needed):
        if not allow_truncated:
            raise incomplete(True, last + 1)
        for b in current:  # drop the incomplete last frame
            if b in rows:
                rows[b].pop()
        frame_numbers.pop()
        if not frame_numbers:
            raise MotionFileError(path, "no complete frame in the file", line=last + 1)
    n = len(frame_numbers)
    values = {b: np.asarray(r, dtype=np.float64).reshape(n, len(asf.dofs[b])) for b, r in rows.items()}
    return n, values


def _check_bone_line(path: Path, tokens: list[str], text: str, lineno: int, asf: AsfSkeleton,
                     frame_numbers: list[int], current: dict[str, int]) -> None:
    """Raise unless this line may name a bone here: no header keyword, inside a frame, a bone of
    the ASF, not yet given in this frame."""
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


def _bone_values(path: Path, tokens: list[str], lineno: int, asf: AsfSkeleton, *, cut: bool,
                 allow_truncated: bool) -> list[float] | None:
    """The values of a bone line, one finite number per dof of its bone. cut: the file's last line
    (a cut-off file ends mid-line); None when it is cut short and allow_truncated."""
    name = tokens[0]
    dofs = asf.dofs[name]
    if len(tokens) - 1 != len(dofs):
        if cut and allow_truncated and len(tokens) - 1 < len(dofs):
            return None
        raise MotionFileError(path, f"bone {name!r} has {len(tokens) - 1} value(s) but its ASF dofs "
                              f"({' '.join(dofs) or 'none'}) need {len(dofs)}"
                              f"{' (the file seems truncated)' if cut else ''}", line=lineno)
    try:
        vals = [float(t) for t in tokens[1:]]
    except ValueError:
        if cut and allow_truncated:
            return None
        bad = next(t for t in tokens[1:] if not _is_float(t))
        raise MotionFileError(path, f"non-numeric value {bad[:30]!r} for bone {name!r}", line=lineno) from None
    if not all(math.isfinite(v) for v in vals):
        raise MotionFileError(path, f"NaN or infinite value for bone {name!r}", line=lineno)
    return vals


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _to_motion(path: Path, asf: AsfSkeleton, frames: int, values: dict[str, np.ndarray], degrees: bool,
               fps: float) -> Motion:
    """Turn per-bone dof values into local quaternions, root positions and (if needed) offsets."""
    local = _local_rotations(asf, frames, values, degrees)
    root_positions, joint_offsets = _translations(asf, frames, values)
    try:
        return Motion(skeleton=asf.skeleton, rotations=local.float(), root_positions=root_positions,
                      fps=float(fps), joint_offsets=joint_offsets, name=file_stem(path, ".amc"))
    except ValueError as error:  # values too large for float32 end up infinite
        raise MotionFileError(path, f"values out of range: {error}") from None


def _local_rotations(asf: AsfSkeleton, frames: int, values: dict[str, np.ndarray], degrees: bool) -> torch.Tensor:
    """(T, J, 4) float64 local rotations C @ M @ C^-1, M from the rotation dofs, C the joint's axis."""
    names = asf.skeleton.names
    joints = len(names)
    # Motion rotations M, batched. Rotation dofs in x, y, z order (any subset) all go through one
    # extrinsic "xyz" conversion, absent axes at zero angle; other orders get one call each.
    local = rot.quat_identity(frames, joints, dtype=torch.float64)
    groups: dict[str, list[int]] = {}
    for j, name in enumerate(names):
        axes_used = "".join(d[1] for d in asf.dofs[name] if d in ROTATION_DOFS)  # "xz": extrinsic
        if axes_used:
            groups.setdefault(axes_used if axes_used not in ("x", "y", "z", "xy", "xz", "yz") else "xyz", []).append(j)
    for convention, members in groups.items():
        angles = np.zeros((frames, len(members), len(convention)))
        for m, j in enumerate(members):
            dofs = asf.dofs[names[j]]
            for i, d in enumerate(dofs):
                if d in ROTATION_DOFS:
                    angles[:, m, convention.index(d[1])] = values[names[j]][:, i]
        local[:, members] = rot.euler_to_quat(convention, torch.from_numpy(angles), degrees=degrees)
    # Conjugate by each joint's axis rotation C (skipping identities): local = C M C^-1.
    axes_all = torch.as_tensor(asf.axis_rotations, dtype=torch.float64)
    turned = [j for j in range(joints) if asf.dofs[names[j]] and abs(float(axes_all[j, 0])) < 1.0 - 1e-15]
    if turned:
        axes = axes_all[turned].expand(frames, len(turned), 4)
        local[:, turned] = rot.quat_mul(rot.quat_mul(axes, local[:, turned]), rot.quat_inv(axes))
    return local


def _translations(asf: AsfSkeleton, frames: int, values: dict[str, np.ndarray]):
    """(root positions (T, 3), joint offsets (T, J, 3) or None when no bone translates or stretches):
    the root's tx ty tz added to its ASF position; a bone's tx ty tz move its joint by C @ t, its
    "l" moves its children along the bone's direction."""
    skeleton, metres = asf.skeleton, asf.metres_per_unit
    axes_all = torch.as_tensor(asf.axis_rotations, dtype=torch.float64)
    root_positions = np.repeat(asf.root_position[None], frames, axis=0)
    joint_offsets = None
    for j, name in enumerate(skeleton.names):
        dofs = asf.dofs[name]
        if not any(d in TRANSLATION_DOFS or d == "l" for d in dofs):
            continue
        v = values[name]
        t = np.zeros((frames, 3))
        moved = False
        for i, d in enumerate(dofs):
            if d in TRANSLATION_DOFS:
                t[:, TRANSLATION_DOFS.index(d)] = v[:, i] * metres
                moved = True
        if j == 0:
            root_positions = root_positions + t
            continue
        if joint_offsets is None:
            joint_offsets = np.repeat(skeleton.offsets[None].double().numpy(), frames, axis=0)
        if moved:
            joint_offsets[:, j] += rot.quat_apply(axes_all[j].expand(frames, 4), torch.from_numpy(t)).numpy()
        if "l" in dofs:
            stretch = v[:, dofs.index("l")] * metres
            for child in skeleton.children(j):
                joint_offsets[:, child] += stretch[:, None] * asf.directions[name]
    return root_positions, joint_offsets
