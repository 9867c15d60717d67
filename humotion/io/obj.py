"""Wavefront OBJ export of a triangle mesh (positions, smooth vertex normals, triangles).

    write_obj("body.obj", vertices, faces)        # (V, 3) metres, (T, 3) vertex indices

Axes and units are written as given (humotion: metres, Y up, facing +Z; Blender's and most
importers' OBJ defaults read Y up). Faces must wind counter-clockwise seen from outside.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from humotion.io.paths import write_atomic


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit vertex normals of a triangle mesh: the area-weighted mean of the normals of
    the faces around each vertex ((0, 1, 0) for a vertex on no face or only degenerate ones).

    vertices (V, 3); faces (faces, 3) vertex indices, counter-clockwise seen from outside. float64."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    face_normals = np.cross(v1 - v0, v2 - v0)  # length = 2 x area
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 1e-12, normals / np.maximum(length, 1e-12), [0.0, 1.0, 0.0])


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, *, name: str = "mesh") -> None:
    """Write a triangle mesh as OBJ: one object `name`, `v` and `vn` lines (smooth normals of
    :func:`vertex_normals`, 6 decimals = micrometres) and `f v//vn` triangles (1-based).

    vertices (V, 3) in metres; faces (faces, 3) vertex indices. Written under a temporary name and
    renamed, so a failure never leaves a half-written file. ValueError for bad shapes or indices."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"write_obj needs vertices (V, 3) and faces (T, 3), got {vertices.shape} and {faces.shape}")
    if not np.isfinite(vertices).all():
        raise ValueError("write_obj: vertices contain NaN or infinite values")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"write_obj: face indices must lie in [0, {len(vertices) - 1}]")
    out = io.StringIO()
    out.write(f"# humotion mesh: {len(vertices)} vertices, {len(faces)} triangles; metres, Y up, facing +Z\n")
    out.write(f"o {name}\n")
    np.savetxt(out, vertices, fmt="v %.6f %.6f %.6f")
    np.savetxt(out, vertex_normals(vertices, faces), fmt="vn %.6f %.6f %.6f")
    one_based = faces + 1
    np.savetxt(out, np.repeat(one_based, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
    write_atomic(path, out.getvalue().encode("ascii"))


__all__ = ["vertex_normals", "write_obj"]
