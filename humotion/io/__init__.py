"""Motion files: read any supported format by its name, write BVH or glTF.

Supported: BVH (.bvh), Acclaim ASF/AMC (.amc with its .asf), the CMU exp-map text format of
cmu_expmap_li2018 (.txt with its skeleton.json), glTF 2.0 animations (.glb, .gltf; written by
humotion.io.gltf.write_gltf, read back by read_gltf_animation); each may be gzip-compressed
(.bvh.gz, ...); AMASS's SMPL-H parameter files (.npz, humotion.io.amass, onto the canonical body).
"""

from __future__ import annotations

from pathlib import Path

from humotion.io.errors import MotionFileError, base_suffix
from humotion.motion import Motion

READABLE = (".bvh", ".amc", ".txt", ".glb", ".gltf", ".npz")
WRITABLE = (".bvh", ".glb", ".gltf")


def load_motion(path: str | Path, *, asf: str | Path | None = None, fps: float | None = None,
                units: str | float = "auto") -> Motion:
    """Read a motion file of any supported format into a Motion (metres, Y up, +Z forward).

    asf: the ASF skeleton for an AMC file (found next to it or in ../asf/ when omitted).
    fps: frame rate for formats that do not store one (AMC, exp-map; default 120 Hz, CMU's rate);
        for glTF, the rate to sample the animation at (default the file's).
    units: BVH length unit ('auto', 'm', 'cm', 'mm', 'inch', 'cmu' or metres per file unit).
    AMASS .npz files keep their own frame rate; their bone lengths come from the SMPL-H model
    named by $HUMOTION_SMPLH_MODEL when set (humotion.io.amass.read_amass for more choices).
    Raises MotionFileError naming the file, line and problem.
    """
    suffix = base_suffix(path)
    if suffix == ".bvh":
        from humotion.io.bvh import read_bvh
        return read_bvh(path, units=units)
    if suffix == ".amc":
        from humotion.io.asf_amc import read_amc
        return read_amc(path, asf=asf, fps=fps or 120.0)
    if suffix == ".txt":
        from humotion.io.expmap import read_expmap
        return read_expmap(path, fps=fps or 120.0)
    if suffix in (".glb", ".gltf"):
        from humotion.io.gltf import read_gltf_animation
        return read_gltf_animation(path, fps=fps)
    if suffix == ".npz":
        from humotion.io.amass import read_amass
        return read_amass(path)
    raise MotionFileError(path, f"unknown motion format {suffix!r}; readable: {', '.join(READABLE)} (optionally .gz)")


def save_motion(motion: Motion, path: str | Path) -> None:
    """Write a Motion; the format follows the suffix (.bvh, .glb, .gltf)."""
    suffix = base_suffix(path)
    if suffix == ".bvh":
        from humotion.io.bvh import write_bvh
        return write_bvh(motion, path)
    if suffix in (".glb", ".gltf"):
        from humotion.io.gltf import write_gltf
        return write_gltf(motion, path)
    raise MotionFileError(path, f"cannot write {suffix!r} files; writable: {', '.join(WRITABLE)}")


__all__ = ["MotionFileError", "load_motion", "save_motion", "READABLE", "WRITABLE"]
