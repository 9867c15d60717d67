"""glTF 2.0 export of a Motion (.glb or .gltf), and reading such animations back.

What write_gltf writes (the container itself is built by pygltflib):
- Axes and units: none converted. glTF is right-handed, +Y up, metres, and "the front of a glTF
  asset faces +Z" (glTF 2.0 specification, section 3.4 "Coordinate System and Units"): exactly
  humotion's conventions (skeleton.py), so every offset and position is written as it is.
- One node per joint, nodes 0..J-1 in skeleton order (node j is joint j), each holding its rest
  offset as translation and no rotation, so the node hierarchy at rest is the skeleton's rest pose.
  End sites follow as leaf nodes J..J+E-1 (translation = end-site offset, never animated).
- A skin over all J+E nodes (end sites included, so importers draw them as tip bones) with
  inverse bind matrices of that rest pose: that is what makes importers treat the hierarchy as
  an armature / skeleton rather than loose empties (checked in Blender and three.js; Unity and
  Unreal were not available to check).
- A stick-figure mesh (mesh=True, default): one small octahedral "bone" shape per bone (parent
  joint to child joint or end site), rigidly bound to its parent joint, a few hundred vertices.
  Why: Blender and three.js do build an armature from a skin alone (checked), but a skin that
  no mesh node uses is referenced by nothing (the Khronos validator reports it as unused), and
  game-engine importers (Unreal's, Unity's) are built around skinned meshes: with one they
  create a skeleton and an animation clip for it, without one at best a plain hierarchy of
  transforms. The mesh node sits at the scene root without a transform, as the specification
  requires of skinned meshes. mesh=False writes the bare armature (nodes, skin, animation).
- Or a mesh of your own (mesh=SkinnedMesh(...), e.g. a body of humotion.body): its rest-pose
  vertices, triangles, optional normals and a material, skinned with each vertex's 4 (or 8)
  heaviest weights renormalised (:func:`skin_influences`; JOINTS_0/WEIGHTS_0, and _1 for 8), and
  optional morph targets with per-frame weights: offsets blended before skinning (glTF 2.0
  section 3.7.2.2), which is how pose-dependent corrective shapes travel in a glTF file.
- One animation: for every joint a rotation channel (quaternions x, y, z, w, sign-continuous
  so LINEAR slerp takes the short way between neighbouring frames), a translation channel for
  the root (Motion.root_positions), translation channels for the other joints when
  Motion.joint_offsets is not None, LINEAR interpolation, key k at k / fps seconds. All channels
  share one time accessor, which carries min/max as the specification requires. The frame rate
  is also kept in the animation's extras ({"fps": ...}) so reading back is exact. A mesh's
  morph targets get a "weights" channel on its node (the same times, LINEAR).
- Names: glTF node names are the joint and end-site names; the skin (Blender names the
  armature after it) and the animation are named after Motion.name.

Checked on the bundled demo clip: the Khronos glTF-Validator 2.0.0-dev.3.10 reports no errors,
warnings, infos or hints; Blender 5.0 (bpy) imports one 38-bone armature with its action, and
three.js r187 (GLTFLoader + AnimationMixer) 38 bones and a skinned mesh; in both the bone world
positions agree with Motion.world_positions() to < 1e-6 m on all 240 frames. Bodies written by
`humotion body` (a skinned mesh with 32 animated morph targets, 4 or 8 influences, low and full
resolution): the validator reports no issues, and with 4 influences three.js r187 (GLTFLoader,
AnimationMixer, SkinnedMesh.getVertexPosition) poses the vertices as tests/test_body_command.py's
own skinning of the file does, to < 1e-6 m (three.js reads only JOINTS_0/WEIGHTS_0, and
renormalises them, so it shows an 8-influence file as its 4 heaviest).

read_gltf_animation reads those files back, and also simple files made elsewhere: one animation
on a node hierarchy (skinned or not) with rotation/translation channels, LINEAR or STEP (and
CUBICSPLINE, whose keyframe values are then interpolated linearly). The joints are the animated
nodes (and the joints of skins that use any of them) with the nodes between them and their lowest
common ancestor, which becomes the root; a leaf of that tree without channels becomes an end
site. Transforms above the root (rigid, or with a uniform scale) are folded into the root and the
lengths. Node scale below the root, scale animation, morph weights and sparse accessors are not
supported and raise MotionFileError.

The pieces humotion.io.character reads and writes whole characters with (any glTF 2.0 / VRM file):

    gltf, buffers = read_gltf_document(path)          # the document and each buffer's bytes
    values = accessor_values(path, gltf, buffers, i)  # (count, components) float64
    translation, wxyz, scale = node_transform(path, gltf.nodes[n], n)
    parent = node_parents(gltf, path)                 # child node -> parent node
    blob = BinaryBuffer(gltf); index = blob.add(array, "VEC3")   # writing: accessors into one buffer
    quats = sign_continuous(quats)                    # (T, J, 4), for LINEAR interpolation
"""

from __future__ import annotations

import base64
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib as gl
import roma
import torch

from humotion import __version__
from humotion import rotations as rot
from humotion.io.errors import MotionFileError, base_suffix, read_bytes
from humotion.io.paths import write_atomic
from humotion.motion import Motion
from humotion.skeleton import Skeleton

SUFFIXES = (".glb", ".gltf")

_GLB_MAGIC = b"glTF"
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_COMPONENT_DTYPES = {gl.BYTE: np.int8, gl.UNSIGNED_BYTE: np.uint8, gl.SHORT: np.int16,
                     gl.UNSIGNED_SHORT: np.uint16, gl.UNSIGNED_INT: np.uint32, gl.FLOAT: np.float32}


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------
class BinaryBuffer:
    """The binary buffer (buffer 0) of a glTF document under construction: add() appends an array
    as one accessor with its own bufferView, each 4-byte aligned; data holds the bytes so far (for
    gltf.set_binary_blob, or a data URI)."""

    def __init__(self, gltf: gl.GLTF2):
        self.gltf = gltf
        self.data = bytearray()

    def add(self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False,
            name: str | None = None) -> int:
        """Append array (count, components) or (count,), of float32, uint8, uint16 or uint32, as an
        accessor of type kind ("SCALAR", "VEC3", "MAT4", ...), with min/max when bounds; return its
        accessor index."""
        array = np.ascontiguousarray(array)
        component = {np.dtype(np.float32): gl.FLOAT, np.dtype(np.uint8): gl.UNSIGNED_BYTE,
                     np.dtype(np.uint16): gl.UNSIGNED_SHORT, np.dtype(np.uint32): gl.UNSIGNED_INT}[array.dtype]
        count = array.shape[0]
        flat = array.reshape(count, -1)
        offset = len(self.data)
        self.data += flat.tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        self.gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=offset, byteLength=flat.nbytes, target=target))
        accessor = gl.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component, count=count,
                               type=kind, normalized=None, name=name)
        if bounds:  # exact values of the stored numbers (float32 widened to float64 is exact)
            accessor.min = [v.item() for v in flat.min(axis=0)]
            accessor.max = [v.item() for v in flat.max(axis=0)]
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


def sign_continuous(q: torch.Tensor) -> torch.Tensor:
    """Quaternions q (T, J, 4) with signs flipped so neighbouring frames have a positive dot
    product (the same rotations), so that LINEAR interpolation between keys takes the short way."""
    if q.shape[0] < 2:
        return q
    dots = (q[1:] * q[:-1]).sum(-1)
    flips = torch.cumprod(torch.where(dots < 0, -1.0, 1.0).to(q.dtype), dim=0)
    return torch.cat([q[:1], q[1:] * flips[..., None]], dim=0)


def _bone_shape(head: np.ndarray, tail: np.ndarray, ring: float, width: float) -> tuple[np.ndarray, np.ndarray]:
    """An octahedron from head to tail (Blender's bone glyph): 6 vertices, 8 outward triangles.

    ring: fraction of the way from head to tail where the square cross-section sits; width: its
    half-diagonal in metres.
    """
    axis = tail - head
    direction = axis / np.linalg.norm(axis)
    helper = np.eye(3)[np.argmin(np.abs(direction))]
    u = np.cross(direction, helper)
    u /= np.linalg.norm(u)
    v = np.cross(direction, u)  # (u, v, direction) right-handed
    centre = head + ring * axis
    vertices = np.stack([head, tail, centre + width * u, centre + width * v, centre - width * u, centre - width * v])
    faces = [(1, 2 + i, 2 + (i + 1) % 4) for i in range(4)] + [(0, 2 + (i + 1) % 4, 2 + i) for i in range(4)]
    return vertices, np.array(faces)


def _stick_figure(skeleton: Skeleton) -> "SkinnedMesh":
    """Octahedral bones of the skeleton's rest pose, each vertex rigidly bound to one joint."""
    rest, ends = skeleton.rest_positions(torch.float64).numpy(), skeleton.rest_end_site_positions(torch.float64).numpy()
    bones = [(p, rest[p], rest[j]) for j, p in enumerate(skeleton.parents) if p >= 0]
    bones += [(p, rest[p], point) for p, point in zip(skeleton.end_site_parents, ends)]
    vertices, faces, owners = [], [], []
    has_bone = set()

    def add(joint: int, shape: tuple[np.ndarray, np.ndarray]) -> None:
        faces.append(shape[1] + 6 * len(vertices))
        vertices.append(shape[0])
        owners.append(np.full(6, joint))

    for joint, head, tail in bones:
        length = float(np.linalg.norm(tail - head))
        if length > 1e-6:
            add(joint, _bone_shape(head, tail, 0.1, 0.1 * length))
            has_bone.add(joint)
    for joint in range(skeleton.num_joints):  # joints with no bone of their own: a 2 cm diamond
        if joint not in has_bone:
            up = np.array([0.0, 0.01, 0.0])
            add(joint, _bone_shape(rest[joint] - up, rest[joint] + up, 0.5, 0.01))
    owners = np.concatenate(owners)
    weights = np.zeros((len(owners), skeleton.num_joints + len(skeleton.end_site_parents)))
    weights[np.arange(len(owners)), owners] = 1.0
    return SkinnedMesh(np.concatenate(vertices), np.concatenate(faces), weights, name="stick_figure")


@dataclass
class SkinnedMesh:
    """A triangle mesh for :func:`write_gltf` to skin to the motion's skeleton.

    vertices (V, 3): positions in the skeleton's rest pose (the bind pose), metres.
    faces (faces, 3): vertex indices, counter-clockwise seen from outside.
    weights (V, N): skinning weights over the skin's joints (the skeleton's J joints, then its
        E end sites: N = J + E), non-negative, rows summing to 1.
    influences: joints kept per vertex in the file, 4 (JOINTS_0/WEIGHTS_0, what every importer
        reads) or 8 (also JOINTS_1/WEIGHTS_1; Blender and Unreal read them, three.js only the
        first four); see :func:`skin_influences`.
    normals (V, 3): unit rest-pose vertex normals, or None (viewers then shade flat).
    morph_targets (M, V, 3): position offsets in metres, blended before skinning, with
    morph_weights (T, M): their weights on each of the motion's T frames (an animation channel);
        both None for a mesh without morph targets. morph_names (M,): their names (Blender's
        shape keys), default target_00, target_01, ...
    color: RGB base colour in [0, 1] of a plain non-metallic material, or None (no material).
    name: the mesh's name (its node is named "<motion name>_<name>"); extras: JSON-ready facts
        kept in the mesh's extras.
    """

    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    influences: int = 4
    normals: np.ndarray | None = None
    morph_targets: np.ndarray | None = None
    morph_weights: np.ndarray | None = None
    morph_names: list[str] | None = None
    color: tuple[float, float, float] | None = None
    name: str = "mesh"
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        V = len(self.vertices)
        if np.shape(self.vertices) != (V, 3) or np.ndim(self.faces) != 2 or np.shape(self.faces)[1] != 3:
            raise ValueError(f"SkinnedMesh needs vertices (V, 3) and faces (T, 3), got {np.shape(self.vertices)} "
                             f"and {np.shape(self.faces)}")
        if self.normals is not None and np.shape(self.normals) != (V, 3):
            raise ValueError(f"SkinnedMesh normals must be (V={V}, 3), got {np.shape(self.normals)}")
        if np.ndim(self.weights) != 2 or len(self.weights) != V:
            raise ValueError(f"SkinnedMesh weights must be (V={V}, joints), got {np.shape(self.weights)}")
        if self.influences not in (4, 8):
            raise ValueError(f"SkinnedMesh influences must be 4 or 8, got {self.influences}")
        if (self.morph_targets is None) != (self.morph_weights is None):
            raise ValueError("SkinnedMesh morph_targets and morph_weights go together")
        if self.morph_targets is not None:
            M = len(self.morph_targets)
            if np.shape(self.morph_targets) != (M, V, 3) or np.ndim(self.morph_weights) != 2 \
                    or np.shape(self.morph_weights)[1] != M:
                raise ValueError(f"SkinnedMesh morph_targets must be (M, V={V}, 3) and morph_weights (T, M), got "
                                 f"{np.shape(self.morph_targets)} and {np.shape(self.morph_weights)}")
            self.morph_names = self.morph_names or [f"target_{m:02d}" for m in range(M)]
            if len(self.morph_names) != M:
                raise ValueError(f"SkinnedMesh has {M} morph targets but {len(self.morph_names)} morph_names")
        arrays = [self.vertices, self.weights] + [a for a in (self.normals, self.morph_targets, self.morph_weights)
                                                  if a is not None]
        if not all(np.isfinite(a).all() for a in arrays):
            raise ValueError("SkinnedMesh holds NaN or infinite values")
        faces = np.asarray(self.faces)
        if len(faces) and (faces.min() < 0 or faces.max() >= V):
            raise ValueError(f"SkinnedMesh face indices must lie in [0, {V - 1}]")
        weights = np.asarray(self.weights)
        if (weights < 0).any() or not np.allclose(weights.sum(1), 1.0, atol=1e-4):
            raise ValueError("SkinnedMesh weights must be non-negative with rows summing to 1")


def skin_influences(weights: np.ndarray, count: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A vertex's `count` heaviest joints, as glTF skins store them.

    weights (V, N) -> joints (V, count) int64 and weights (V, count) float32, heaviest first,
    renormalised to sum to 1 (to float32 rounding: the residue goes to the heaviest). Slots
    without weight get joint 0, as the glTF specification asks of unused influences. Weight on
    further joints is dropped; weights fitted to `count` joints beforehand skin more faithfully
    (as :mod:`humotion.body.skin_export` does for the body model)."""
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape[1] < count:
        weights = np.pad(weights, ((0, 0), (0, count - weights.shape[1])))
    joints = np.argsort(-weights, axis=1, kind="stable")[:, :count]
    kept = np.take_along_axis(weights, joints, axis=1)
    kept = (kept / kept.sum(1, keepdims=True)).astype(np.float32)
    kept[:, 0] += np.float32(1.0) - kept.sum(1, dtype=np.float32)
    return np.where(kept > 0, joints, 0), kept


def _add_mesh(gltf: gl.GLTF2, blob: BinaryBuffer, mesh: SkinnedMesh, skin_joints: int, node_name: str) -> int:
    """Add a skinned mesh (primitive, optional material and morph targets) and the scene-root
    node that holds it with skin 0; return the node's index."""
    if np.shape(mesh.weights)[1] != skin_joints:
        raise ValueError(f"mesh {mesh.name!r}: weights over {np.shape(mesh.weights)[1]} joints, the skin has {skin_joints}")
    joints, weights = skin_influences(mesh.weights, mesh.influences)
    joints = joints.astype(np.uint8 if skin_joints <= 256 else np.uint16)
    attributes = gl.Attributes(POSITION=blob.add(np.asarray(mesh.vertices, np.float32), "VEC3",
                                                 target=gl.ARRAY_BUFFER, bounds=True))
    if mesh.normals is not None:
        attributes.NORMAL = blob.add(np.asarray(mesh.normals, np.float32), "VEC3", target=gl.ARRAY_BUFFER)
    for k in range(mesh.influences // 4):
        setattr(attributes, f"JOINTS_{k}", blob.add(joints[:, 4 * k:4 * k + 4], "VEC4", target=gl.ARRAY_BUFFER))
        setattr(attributes, f"WEIGHTS_{k}", blob.add(weights[:, 4 * k:4 * k + 4], "VEC4", target=gl.ARRAY_BUFFER))
    faces = np.asarray(mesh.faces).reshape(-1)
    indices = blob.add(faces.astype(np.uint16 if len(mesh.vertices) < 65535 else np.uint32), "SCALAR",
                       target=gl.ELEMENT_ARRAY_BUFFER)
    primitive = gl.Primitive(attributes=attributes, indices=indices)
    extras = dict(mesh.extras)
    weights_default = []
    if mesh.morph_targets is not None:
        primitive.targets = [gl.Attributes(POSITION=blob.add(np.asarray(t, np.float32), "VEC3", target=gl.ARRAY_BUFFER,
                                                             bounds=True)) for t in mesh.morph_targets]
        weights_default = [0.0] * len(mesh.morph_targets)
        extras["targetNames"] = list(mesh.morph_names)  # the de facto convention for morph target names
    if mesh.color is not None:
        gltf.materials.append(gl.Material(name=mesh.name, pbrMetallicRoughness=gl.PbrMetallicRoughness(
            baseColorFactor=[float(c) for c in mesh.color] + [1.0], metallicFactor=0.0, roughnessFactor=0.6)))
        primitive.material = len(gltf.materials) - 1
    gltf.meshes.append(gl.Mesh(name=mesh.name, primitives=[primitive], weights=weights_default, extras=extras))
    gltf.nodes.append(gl.Node(name=node_name, mesh=len(gltf.meshes) - 1, skin=0))
    return len(gltf.nodes) - 1


def _json_floats(values: torch.Tensor) -> list[float]:
    """float32 values as the shortest decimals that read back as the same float32 (0.1, not
    0.10000000149011612), for the JSON part of a glTF file."""
    return [float(str(x)) for x in values.numpy()]


def write_gltf(motion: Motion, path: str | Path, *, mesh: bool | SkinnedMesh = True) -> None:
    """Write a Motion as a glTF 2.0 skeletal animation (see the module docstring for the layout).

    path: .glb writes the binary container, .gltf JSON with the buffer embedded as a base64
        data URI (one self-contained file either way); a trailing .gz gzip-compresses it (which
        only humotion reads back). Lengths in metres, Y up, +Z forward: no axis conversion.
    mesh: True: the stick-figure skinned mesh (needed by Unreal/Unity to create a skeleton);
        False: none; a SkinnedMesh: that mesh (its morph_weights, if any, one row per frame).
    The file is written under a temporary name beside path and renamed, so a failure never
    leaves a half-written file. Raises ValueError for another suffix or a mesh that does not fit.
    """
    path = Path(path)
    suffix = base_suffix(path)
    if suffix not in SUFFIXES:
        raise ValueError(f"write_gltf writes .glb or .gltf files, not {suffix!r} ({path})")
    skeleton = motion.skeleton
    joints, ends, frames = skeleton.num_joints, len(skeleton.end_site_parents), motion.num_frames

    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator=f"humotion {__version__} (pygltflib {gl.__version__})"))
    blob = BinaryBuffer(gltf)

    # nodes: joints in skeleton order, then end sites
    children: list[list[int]] = [[] for _ in range(joints)]
    for j, p in enumerate(skeleton.parents):
        if p >= 0:
            children[p].append(j)
    for e, p in enumerate(skeleton.end_site_parents):
        children[p].append(joints + e)
    for j in range(joints):
        gltf.nodes.append(gl.Node(name=skeleton.names[j], translation=_json_floats(skeleton.offsets[j]),
                                  children=children[j]))
    for e in range(ends):
        gltf.nodes.append(gl.Node(name=skeleton.end_site_names[e],
                                  translation=_json_floats(skeleton.end_site_offsets[e])))

    # skin: inverse bind matrices of the rest pose (every rest rotation is the identity, so each
    # is a translation by minus the rest world position), stored column-major as glTF requires
    rest = skeleton.rest_points().numpy()
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (joints + ends, 1, 1))
    inverse_bind[:, :3, 3] = -rest
    ibm = blob.add(inverse_bind.transpose(0, 2, 1).reshape(-1, 16), "MAT4", name="inverse_bind_matrices")
    gltf.skins.append(gl.Skin(name=motion.name or "skeleton", inverseBindMatrices=ibm, skeleton=0,
                              joints=list(range(joints + ends))))
    scene_nodes = [0]

    if mesh is True:
        mesh = _stick_figure(skeleton)
    if isinstance(mesh, SkinnedMesh):
        if mesh.morph_weights is not None and len(mesh.morph_weights) != frames:
            raise ValueError(f"mesh {mesh.name!r}: morph weights for {len(mesh.morph_weights)} frames, "
                             f"the motion has {frames}")
        scene_nodes.append(_add_mesh(gltf, blob, mesh, joints + ends, f"{motion.name or 'skeleton'}_{mesh.name}"))
    gltf.scenes.append(gl.Scene(name=motion.name or "motion", nodes=scene_nodes))
    gltf.scene = 0

    # animation
    animation = gl.Animation(name=motion.name or "motion", extras={"fps": float(motion.fps)})
    times = blob.add((np.arange(frames, dtype=np.float64) / motion.fps).astype(np.float32), "SCALAR",
                     bounds=True, name="time")

    def channel(node: int, target: str, values: np.ndarray) -> None:
        animation.samplers.append(gl.AnimationSampler(input=times, output=blob.add(values, _kind(values)),
                                                      interpolation=gl.ANIM_LINEAR))
        animation.channels.append(gl.AnimationChannel(sampler=len(animation.samplers) - 1,
                                                      target=gl.AnimationChannelTarget(node=node, path=target)))

    quats = sign_continuous(torch.nn.functional.normalize(motion.rotations.detach().cpu().double(), dim=-1))
    xyzw = roma.quat_wxyz_to_xyzw(quats).float().numpy()  # (T, J, 4)
    root = motion.root_positions.detach().cpu().float().numpy()
    offsets = None if motion.joint_offsets is None else motion.joint_offsets.detach().cpu().float().numpy()
    for j in range(joints):
        channel(j, gl.ROTATION, xyzw[:, j])
        if j == 0:
            channel(j, gl.TRANSLATION, root)
        elif offsets is not None:
            channel(j, gl.TRANSLATION, offsets[:, j])
    if isinstance(mesh, SkinnedMesh) and mesh.morph_weights is not None:
        channel(scene_nodes[-1], gl.WEIGHTS, np.asarray(mesh.morph_weights, np.float32).reshape(-1))
    gltf.animations.append(animation)

    data = bytes(blob.data)
    if suffix == ".glb":
        gltf.buffers.append(gl.Buffer(byteLength=len(data)))
        gltf.set_binary_blob(data)
        payload = b"".join(gltf.save_to_bytes())
    else:
        gltf.buffers.append(gl.Buffer(byteLength=len(data),
                                      uri="data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")))
        payload = gltf.gltf_to_json().encode("utf-8")
    write_atomic(path, payload)


def _kind(values: np.ndarray) -> str:
    return {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[values.shape[-1] if values.ndim > 1 else 1]


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
def read_gltf_document(path: str | Path) -> tuple[gl.GLTF2, list[bytes | None]]:
    """The parsed document of a glTF 2.0 file (.glb, .gltf or .vrm, optionally gzip-compressed) and
    the bytes of each of its buffers (a GLB's binary chunk, a data URI's, or a file beside it;
    None for a buffer without data). MotionFileError naming path for a file that is no glTF 2.0."""
    path = Path(path)
    raw = read_bytes(path)
    try:
        if raw[:4] == _GLB_MAGIC:
            if len(raw) < 20:
                raise ValueError("truncated GLB header")
            version, length = struct.unpack("<II", raw[4:12])
            if version != 2:
                raise ValueError(f"GLB container version {version}; only glTF 2.0 is supported")
            if length > len(raw):
                raise ValueError(f"GLB header declares {length} bytes, the file has {len(raw)} (truncated?)")
            gltf = gl.GLTF2.load_from_bytes(raw)
            if gltf is None:
                raise ValueError("GLB file has no JSON chunk")
        else:
            gltf = gl.GLTF2.gltf_from_json(raw.decode("utf-8"))
    except Exception as error:  # pygltflib / dataclasses-json raise assorted types on bad input
        raise MotionFileError(path, f"not a readable glTF 2.0 file ({type(error).__name__}: {error})") from None
    if not str(gltf.asset.version if gltf.asset else "").startswith("2."):
        raise MotionFileError(path, f"glTF version {gltf.asset.version if gltf.asset else None!r}; only 2.x is supported")
    buffers: list[bytes | None] = []
    for i, buffer in enumerate(gltf.buffers):
        if buffer.uri is None:
            buffers.append(gltf.binary_blob() if i == 0 else None)
        elif buffer.uri.startswith("data:"):
            try:
                buffers.append(base64.b64decode(buffer.uri.split(",", 1)[1]))
            except (IndexError, ValueError):
                raise MotionFileError(path, f"buffer {i}: malformed data URI") from None
        else:
            try:
                buffers.append((path.parent / buffer.uri).read_bytes())
            except OSError as error:
                raise MotionFileError(path, f"buffer {i}: cannot read {buffer.uri!r} ({error.strerror or error})") from None
    return gltf, buffers


def accessor_values(path: str | Path, gltf: gl.GLTF2, buffers: list[bytes | None], index: int) -> np.ndarray:
    """The values of accessor index of the document (buffers: read_gltf_document's) as float64
    (N, D): its N elements of D components each (1 for SCALAR, 3 for VEC3, 16 for a column-major
    MAT4), normalised integers mapped to [-1, 1] / [0, 1]. MotionFileError naming path (the file,
    for the message) for a missing, sparse or truncated accessor."""
    try:
        accessor = gltf.accessors[index]
    except (IndexError, TypeError):
        raise MotionFileError(path, f"accessor {index} does not exist") from None
    components = _COMPONENTS.get(accessor.type)
    dtype = _COMPONENT_DTYPES.get(accessor.componentType)
    if components is None or dtype is None:
        raise MotionFileError(path, f"accessor {index}: unsupported type {accessor.type}/{accessor.componentType}")
    if accessor.sparse is not None:
        raise MotionFileError(path, f"accessor {index}: sparse accessors are not supported")
    count = accessor.count or 0
    if accessor.bufferView is None:
        return np.zeros((count, components))
    view = gltf.bufferViews[accessor.bufferView]
    data = buffers[view.buffer] if 0 <= view.buffer < len(buffers) else None
    if data is None:
        raise MotionFileError(path, f"accessor {index}: buffer {view.buffer} has no data")
    item = np.dtype(dtype).itemsize
    stride = view.byteStride or item * components
    start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
    end = start + (stride * (count - 1) + item * components if count else 0)
    if end > (view.byteOffset or 0) + view.byteLength or end > len(data):
        raise MotionFileError(path, f"accessor {index} reaches beyond its buffer view (truncated file?)")
    values = np.ndarray((count, components), dtype=np.dtype(dtype).newbyteorder("<"), buffer=data,
                        offset=start, strides=(stride, item)).astype(np.float64)
    if accessor.normalized and dtype != np.float32:
        info = np.iinfo(dtype)
        values = np.maximum(values / info.max, -1.0)
    return values


def node_transform(path: str | Path, node: gl.Node, index: int) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """The static transform of node (number index, for messages) as translation (3,) float64
    array, rotation (4,) float64 wxyz tensor and scale (3,) float64 array, from its TRS or its
    matrix. MotionFileError naming path for a matrix that is no rotation with positive scale."""
    if node.matrix is not None and not np.allclose(node.matrix, np.eye(4).reshape(-1)):
        m = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major in the file
        scale = np.linalg.norm(m[:3, :3], axis=0)
        if not (scale > 1e-12).all() or np.linalg.det(m[:3, :3]) <= 0:
            raise MotionFileError(path, f"node {index} ({node.name!r}): matrix is not a rotation with positive scale")
        quat = rot.matrix_to_quat(torch.from_numpy(m[:3, :3] / scale))
        return m[:3, 3].copy(), quat, scale
    translation = np.asarray(node.translation if node.translation is not None else [0.0, 0.0, 0.0], dtype=np.float64)
    xyzw = torch.tensor(node.rotation if node.rotation is not None else [0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    scale = np.asarray(node.scale if node.scale is not None else [1.0, 1.0, 1.0], dtype=np.float64)
    return translation, roma.quat_xyzw_to_wxyz(torch.nn.functional.normalize(xyzw, dim=-1)), scale


def _sample(times: np.ndarray, values: np.ndarray, interpolation: str, at: np.ndarray, rotation: bool) -> np.ndarray:
    """Values of one sampler at the times at (T,): LINEAR (slerp for rotations), STEP, or
    CUBICSPLINE read as its keyframe values interpolated linearly."""
    if interpolation == "CUBICSPLINE":
        values = values.reshape(len(times), 3, -1)[:, 1]
    if len(times) == 1:
        return np.repeat(values, len(at), axis=0)
    lo = np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 2)
    weight = np.clip((at - times[lo]) / np.maximum(times[lo + 1] - times[lo], 1e-12), 0.0, 1.0)
    weight[weight < 1e-6] = 0.0  # on a key (times are float32): take it exactly
    on_next = weight > 1 - 1e-6
    lo, weight = np.where(on_next, lo + 1, lo), np.where(on_next, 0.0, weight)
    hi = np.minimum(lo + 1, len(times) - 1)
    if interpolation == "STEP":
        return values[lo]
    if rotation:
        q0 = roma.quat_xyzw_to_wxyz(torch.from_numpy(values[lo]))
        q1 = roma.quat_xyzw_to_wxyz(torch.from_numpy(values[hi]))
        return roma.quat_wxyz_to_xyzw(rot.quat_slerp(q0, q1, torch.from_numpy(weight))).numpy()
    return values[lo] * (1 - weight[:, None]) + values[hi] * weight[:, None]


def _frame_rate(times: list[np.ndarray]) -> float:
    """Frame rate of keyframes without a stored one: 1 / the median step of the densest input,
    snapped to a whole number within 0.1%."""
    densest = max(times, key=len)
    if len(densest) < 2:
        return 30.0
    step = float(np.median(np.diff(densest)))
    if step <= 0:
        return 30.0
    fps = 1.0 / step
    return float(round(fps)) if round(fps) >= 1 and abs(round(fps) - fps) < 1e-3 * fps else fps


def node_parents(gltf: gl.GLTF2, path: str | Path) -> dict[int, int]:
    """Each child node's parent index, {child: parent} (roots are absent). Raises MotionFileError
    naming the file when a node is the child of two nodes or a child index does not exist."""
    nodes = gltf.nodes
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        for child in node.children or []:
            if child in parent or not 0 <= child < len(nodes):
                raise MotionFileError(path, f"node {child} is a child of two nodes or does not exist")
            parent[child] = i
    return parent


def read_gltf_animation(path: str | Path, *, animation: int = 0, fps: float | None = None) -> Motion:
    """Read one animation of a glTF 2.0 file (.glb or .gltf, optionally gzip-compressed) as a Motion.

    animation: index of the animation to read (files written by write_gltf have one).
    fps: sampling rate of the result; default the rate stored by write_gltf, else the rate of the
        keyframes (1 / their median spacing). Channels are evaluated at k / fps from the first key.
    Returns joints in node order (the original skeleton order for files write_gltf wrote), end
    sites from unanimated leaves, root_positions from the root's translation, joint_offsets when
    other joints have translation channels. Raises MotionFileError for anything else.
    """
    path = Path(path)
    gltf, buffers = read_gltf_document(path)
    nodes = gltf.nodes
    if not gltf.animations:
        raise MotionFileError(path, "file holds no animation")
    if not 0 <= animation < len(gltf.animations):
        raise MotionFileError(path, f"animation {animation} requested, the file has {len(gltf.animations)}")
    anim = gltf.animations[animation]
    parent = node_parents(gltf, path)

    # channels
    channels: dict[tuple[int, str], tuple[np.ndarray, np.ndarray, str]] = {}
    for c, ch in enumerate(anim.channels):
        target = ch.target
        if target is None or target.node is None or target.path == "weights":
            continue
        if not 0 <= target.node < len(nodes):
            raise MotionFileError(path, f"animation channel {c} targets node {target.node}, which does not exist")
        if not 0 <= ch.sampler < len(anim.samplers):
            raise MotionFileError(path, f"animation channel {c} uses sampler {ch.sampler}, which does not exist")
        sampler = anim.samplers[ch.sampler]
        times = accessor_values(path, gltf, buffers, sampler.input)[:, 0]
        values = accessor_values(path, gltf, buffers, sampler.output)
        interpolation = sampler.interpolation or "LINEAR"
        if interpolation not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise MotionFileError(path, f"animation channel {c}: unknown interpolation {interpolation!r}")
        if len(times) == 0 or len(values) != len(times) * (3 if interpolation == "CUBICSPLINE" else 1):
            raise MotionFileError(path, f"animation channel {c}: {len(times)} key times but {len(values)} values")
        if np.any(np.diff(times) <= 0) or not np.isfinite(times).all():
            raise MotionFileError(path, f"animation channel {c}: key times are not strictly increasing")
        if target.path == "scale":
            if not np.allclose(values, 1.0, atol=1e-4):  # as node scales below
                raise MotionFileError(path, f"animation channel {c} scales node {target.node}; scale animation is not supported")
            continue
        if target.path not in ("rotation", "translation"):
            raise MotionFileError(path, f"animation channel {c}: unknown target path {target.path!r}")
        channels[(target.node, target.path)] = (times, values, interpolation)
    animated = {node for node, _ in channels}
    if not animated:
        raise MotionFileError(path, f"animation {animation} moves no node (no rotation or translation channels)")

    # the joint tree: animated nodes, skin joints of skins using them, the nodes between them
    marked = set(animated)
    for skin in gltf.skins:
        if marked & set(skin.joints or []):
            marked |= set(skin.joints)

    def ancestors(n: int) -> list[int]:
        chain = [n]
        while chain[-1] in parent:
            chain.append(parent[chain[-1]])
        return chain  # n first, scene root last

    chains = [ancestors(n) for n in sorted(marked)]
    common = set(chains[0]).intersection(*map(set, chains[1:]))
    if not common:
        raise MotionFileError(path, "the animated nodes do not share one hierarchy (several roots); not a single skeleton")
    root = next(n for n in chains[0] if n in common)  # lowest common ancestor
    tree = {root}
    for chain in chains:
        tree.update(chain[:chain.index(root)])
    tree_children = {n: [c for c in (nodes[n].children or []) if c in tree] for n in tree}
    end_nodes = {n for n in tree if n != root and not tree_children[n] and n not in animated}
    joint_nodes = [n for n in tree if n not in end_nodes]
    order = sorted(joint_nodes)
    if any(n != root and order.index(parent[n]) > order.index(n) for n in order) or order[0] != root:
        order, stack = [], [root]  # node indices do not list parents first: depth-first order
        while stack:
            n = stack.pop()
            order.append(n)
            stack.extend(reversed([c for c in tree_children[n] if c not in end_nodes]))
    index = {n: j for j, n in enumerate(order)}
    ends = sorted(end_nodes)

    # static transforms
    transforms = {n: node_transform(path, nodes[n], n) for n in tree}
    for n in tree:  # exporters leave scales such as 1.0000156 (float32 rounding of a rotated bone): 1
        if not np.allclose(transforms[n][2], 1.0, atol=1e-4):
            raise MotionFileError(path, f"node {n} ({nodes[n].name!r}) is scaled; only unscaled joints are supported")
    above_r, above_t, above_s = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64), np.zeros(3), 1.0
    for n in ancestors(root)[1:]:  # fold the transforms above the root, innermost first
        t, q, s = node_transform(path, nodes[n], n)
        if not np.allclose(s, s[0], rtol=1e-6):
            raise MotionFileError(path, f"node {n} ({nodes[n].name!r}) above the skeleton has a non-uniform scale")
        above_t = t + s[0] * rot.quat_apply(q, torch.from_numpy(above_t)).numpy()
        above_r, above_s = rot.quat_mul(q, above_r), above_s * float(s[0])

    # frame times
    extras = anim.extras if isinstance(anim.extras, dict) else {}
    stored = extras.get("fps")
    rate = fps or (float(stored) if isinstance(stored, (int, float)) and math.isfinite(stored) and stored > 0 else None)
    rate = rate or _frame_rate([t for t, _, _ in channels.values()])
    start = min(float(t[0]) for t, _, _ in channels.values())
    stop = max(float(t[-1]) for t, _, _ in channels.values())
    frames = int(math.floor((stop - start) * rate + 1e-3)) + 1
    at = start + np.arange(frames, dtype=np.float64) / rate

    def track(node: int, kind: str) -> np.ndarray:
        """(T, 4) xyzw rotation or (T, 3) translation of a node on every frame."""
        if (node, kind) in channels:
            times, values, interpolation = channels[(node, kind)]
            width = 4 if kind == "rotation" else 3
            if values.shape[1] != width:
                raise MotionFileError(path, f"node {node}: {kind} keys have {values.shape[1]} components, expected {width}")
            return _sample(times, values, interpolation, at, kind == "rotation")
        t, q, _ = transforms[node]
        static = roma.quat_wxyz_to_xyzw(q).numpy() if kind == "rotation" else t
        return np.tile(static, (frames, 1))

    names = [nodes[n].name or f"node{n}" for n in order + ends]
    seen: dict[str, int] = {}
    for i, name in enumerate(names):  # joint names must be unique
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:
            names[i] = f"{name}.{seen[name] - 1}"
    offsets = np.stack([transforms[n][0] for n in order]) * above_s
    offsets[0] = above_t + above_s * rot.quat_apply(above_r, torch.from_numpy(transforms[root][0])).numpy()
    rotations = torch.from_numpy(np.stack([track(n, "rotation") for n in order], axis=1))  # (T, J, 4) xyzw
    rotations = torch.nn.functional.normalize(roma.quat_xyzw_to_wxyz(rotations), dim=-1)
    rotations[:, 0] = rot.quat_mul(above_r.expand(frames, 4), rotations[:, 0])
    root_positions = above_t + above_s * rot.quat_apply(above_r.expand(frames, 4), torch.from_numpy(track(root, "translation"))).numpy()
    joint_offsets = None
    if any((n, "translation") in channels for n in order[1:]):
        joint_offsets = np.stack([track(n, "translation") for n in order], axis=1) * above_s
        joint_offsets[:, 0] = offsets[0]
    try:
        skeleton = Skeleton(names[:len(order)], [-1] + [index[parent[n]] for n in order[1:]], offsets,
                            [index[parent[n]] for n in ends],
                            np.array([transforms[n][0] for n in ends]).reshape(-1, 3) * above_s, names[len(order):])
        return Motion(skeleton, rotations.float(), root_positions, float(rate), joint_offsets,
                      name=anim.name or path.name.split(".")[0])
    except ValueError as error:
        raise MotionFileError(path, str(error)) from None


__all__ = ["write_gltf", "read_gltf_animation", "SkinnedMesh", "skin_influences", "SUFFIXES"]
