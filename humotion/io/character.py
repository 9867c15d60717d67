"""Rigged characters (glTF/GLB, VRM 0.x and 1.0, FBX through Blender): their skeleton in, the
character with a new animation out.

read_character reads the skeleton a character is skinned to:
- The joints are the joints of all its skins (several skins sharing one skeleton count once), or
  for a VRM without a skin (rigid parts parented to bones) the nodes of its humanoid bone map,
  plus the nodes between them and their lowest common ancestor, which becomes the root. Nodes
  above the root (a Z-up armature under a Y-up root matrix, an armature scaled by 100) stay as
  they are; their transform is folded into the skeleton, so it stands in the scene's frame.
- The bind pose comes from the skins: a joint's bind transform (in the scene, Y up) is the
  inverse of its inverse bind matrix; joints no skin binds take their parent's bind transform
  times their own node transform. The Skeleton's offsets are each node's translation turned and
  scaled by its parent's bind transform, so forward kinematics on the Skeleton and the glTF node
  hierarchy put every joint in the same place; lengths are in the file's units (glTF: metres).
- A VRM's humanoid bone map (VRM 0.x extensions.VRM.humanoid.humanBones, a list; VRM 1.0
  extensions.VRMC_vrm.humanoid.humanBones, a dict) names the key joints: Character.overrides
  is the override table humotion.retarget.Rig.of takes.

write_character writes the file back with everything it held (meshes, materials, textures, morph
targets, skins, extensions, its own animations) and the motion as its first animation: per
joint node a rotation channel, the root node a translation channel too, LINEAR, key k at
k / fps. A motion on the Skeleton is a rotation W_j of each joint away from the bind pose in the
world frame; the node's rotation is then R_p^T W_p^T W_j R_j (R: the rotation part of the bind
transforms of the joint and its parent p), and the root's is taken through the static transform
above it. .glb/.vrm out is one binary container (buffers merged, images moved into it); .gltf
out is JSON with one base64 buffer.

FBX (.fbx in or out) goes through Blender's own FBX and glTF add-ons, the `bpy` package
(humotion[fbx]): the FBX is converted to a temporary GLB and read as above, and written by
converting the written GLB. Without bpy, .fbx raises MotionFileError naming the extra.
"""

from __future__ import annotations

import base64
import contextlib
import copy
import logging
import mimetypes
import os
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib as gl
import roma
import torch

from humotion import rotations as rot
from humotion.io.errors import MotionFileError, base_suffix
from humotion.io.gltf import (BinaryBuffer, accessor_values, node_parents, node_transform, read_gltf_document,
                              sign_continuous)
from humotion.io.paths import write_atomic
from humotion.motion import Motion
from humotion.skeleton import Skeleton

log = logging.getLogger(__name__)

SUFFIXES = (".glb", ".gltf", ".vrm", ".fbx")

# VRM humanoid bone -> canonical key joint (humotion.canonical.JOINTS); the spine is mapped
# separately (spine / chest / upperChest, whichever the model has).
_VRM_BONES = {"hips": "pelvis", "neck": "neck", "head": "head"}
for _side in ("left", "right"):
    _VRM_BONES.update({f"{_side}Shoulder": f"{_side}_collar", f"{_side}UpperArm": f"{_side}_shoulder",
                       f"{_side}LowerArm": f"{_side}_elbow", f"{_side}Hand": f"{_side}_wrist",
                       f"{_side}UpperLeg": f"{_side}_hip", f"{_side}LowerLeg": f"{_side}_knee",
                       f"{_side}Foot": f"{_side}_ankle", f"{_side}Toes": f"{_side}_foot"})


@dataclass(eq=False)
class Character:
    """A rigged character as read by :func:`read_character`.

    skeleton: J joints in the bind pose (scene frame, Y up, the file's length unit).
    nodes (J,): glTF node of each joint. bind (J, 4, 4): each joint's bind transform in the scene
    (rotation, uniform scale, position). above (4, 4): scene transform of the root node's parent (identity when the
    root is a scene root). moved: nodes whose translation the animation must set (a foot the
    Skeleton hangs under its leg, a translation that is not the bind pose's). overrides: {"joints": key joint -> joint name} from a VRM humanoid
    map, else {}. kind: "glTF", "VRM 0.x", "VRM 1.0" or "FBX". The glTF document and its
    buffers' bytes are kept for writing.
    """

    path: Path
    gltf: gl.GLTF2
    buffers: list[bytes | None]
    skeleton: Skeleton
    nodes: list[int]
    bind: np.ndarray
    above: np.ndarray
    overrides: dict
    kind: str
    moved: list[int]

    @property
    def num_meshes(self) -> int:
        return len(self.gltf.meshes)


def _matrix(t: np.ndarray, q: torch.Tensor, s: np.ndarray) -> np.ndarray:
    """4x4 from translation (3,), rotation wxyz (4,) and scale (3,)."""
    m = np.eye(4)
    m[:3, :3] = rot.quat_to_matrix(q.double()).numpy() * s
    m[:3, 3] = t
    return m


def _similarity(m: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotation (3, 3) and uniform scale of a 4x4 transform's linear part (its nearest rotation
    by SVD when the scale is not uniform)."""
    u, singular, vt = np.linalg.svd(m[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        raise ValueError("a mirrored bind transform")
    return r, float(singular.mean())


def humanoid_bones(gltf: gl.GLTF2) -> tuple[str, dict[str, int]]:
    """A VRM's humanoid map: ("VRM 1.0" | "VRM 0.x" | "glTF", {VRM bone name: node index})."""
    extensions = gltf.extensions or {}
    if isinstance(extensions.get("VRMC_vrm"), dict):
        bones = extensions["VRMC_vrm"].get("humanoid", {}).get("humanBones", {})
        return "VRM 1.0", {b: int(v["node"]) for b, v in bones.items() if isinstance(v, dict) and "node" in v}
    if isinstance(extensions.get("VRM"), dict):
        bones = extensions["VRM"].get("humanoid", {}).get("humanBones", [])
        return "VRM 0.x", {b["bone"]: int(b["node"]) for b in bones
                           if isinstance(b, dict) and "bone" in b and b.get("node", -1) >= 0}
    return "glTF", {}


def _overrides(bones: dict[str, int], names: dict[int, str]) -> dict:
    """Override table (Rig.of) from a VRM humanoid map, for the bones on the skeleton."""
    joints = {key: names[bones[b]] for b, key in _VRM_BONES.items() if bones.get(b) in names}
    spine = [names[bones[b]] for b in ("spine", "chest", "upperChest") if bones.get(b) in names]
    if spine:  # the last is where arms and neck branch (spine3); the others below it
        joints["spine3"] = spine[-1]
        joints.update(zip(("spine1", "spine2"), spine[:-1]))
    return {"joints": joints} if joints else {}


def read_character(path: str | Path) -> Character:
    """The character's skeleton and bind pose (module docstring). Raises MotionFileError for a
    file that is no readable glTF/VRM/FBX or holds no skin and no humanoid bone map."""
    path = Path(path)
    suffix = base_suffix(path)
    if suffix == ".fbx":
        return _read_fbx(path)
    if suffix not in SUFFIXES:
        raise MotionFileError(path, f"not a character file (readable: {', '.join(SUFFIXES)})")
    gltf, buffers = read_gltf_document(path)
    nodes = gltf.nodes
    parent = node_parents(gltf, path)
    kind, bones = humanoid_bones(gltf)

    def ancestors(n: int) -> list[int]:
        return _chain(n, parent)

    def world(n: int) -> np.ndarray:
        m = np.eye(4)
        for a in reversed(ancestors(n)):
            m = m @ _matrix(*node_transform(path, nodes[a], a))
        return m

    bind: dict[int, np.ndarray] = {}
    for s, skin in enumerate(gltf.skins):
        joints = skin.joints or []
        if any(not 0 <= j < len(nodes) for j in joints):
            raise MotionFileError(path, f"skin {s} names a node that does not exist")
        inverse = (accessor_values(path, gltf, buffers, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
                   if skin.inverseBindMatrices is not None else np.tile(np.eye(4), (len(joints), 1, 1)))
        if len(inverse) != len(joints):
            raise MotionFileError(path, f"skin {s}: {len(joints)} joints but {len(inverse)} inverse bind matrices")
        # the mesh's vertices are in its node's frame (as three.js and Blender read them)
        user = next((i for i, node in enumerate(nodes) if node.skin == s), None)
        mesh_world = world(user) if user is not None else np.eye(4)
        for j, m in zip(joints, inverse):
            bind.setdefault(j, mesh_world @ np.linalg.inv(m))
    marked = set(bind) or {n for n in bones.values() if 0 <= n < len(nodes)}
    if not marked:
        raise MotionFileError(path, "no skin and no VRM humanoid bone map: not a rigged character")
    chains = [ancestors(n) for n in sorted(marked)]
    common = set(chains[0]).intersection(*map(set, chains[1:]))
    if not common:
        raise MotionFileError(path, "the skin's joints do not share one hierarchy (several roots)")
    root = next(n for n in chains[0] if n in common)
    tree = {root}
    for chain in chains:
        tree.update(chain[:chain.index(root)])
    above = world(parent[root]) if root in parent else np.eye(4)
    local = {n: _matrix(*node_transform(path, nodes[n], n)) for n in nodes_below(nodes, root)}
    order, stack = [], [root]  # depth first: parents before children
    while stack:
        n = stack.pop()
        order.append(n)
        if n not in bind:
            bind[n] = (bind[parent[n]] if n != root else above) @ local[n]
        stack.extend(reversed([c for c in nodes[n].children or [] if c in tree]))
    try:
        for n in order:
            _similarity(bind[n])
    except ValueError as error:
        raise MotionFileError(path, str(error)) from None
    names, seen = [], set()
    for n in order:
        name = nodes[n].name or f"node{n}"
        while name in seen:
            name += "_"
        seen.add(name)
        names.append(name)
    hubs = _palms_on_hub(order, bind, parent)
    rig_parent = {n: parent[n] for n in order[1:]} | _reattached_feet(order, names, bind, parent) | hubs
    index = {n: j for j, n in enumerate(order)}
    parents = [-1] + [index[rig_parent[n]] for n in order[1:]]
    if any(p >= j for j, p in enumerate(parents)):  # a reattached foot listed before its leg
        order = sorted(order, key=lambda n: len(_chain(n, rig_parent)))
        names = [names[index[n]] for n in order]
        index = {n: j for j, n in enumerate(order)}
        parents = [-1] + [index[rig_parent[n]] for n in order[1:]]
    position = np.stack([bind[n][:3, 3] for n in order])
    offsets = np.stack([position[0]] + [position[j] - position[p] for j, p in enumerate(parents) if p >= 0])
    ends = _end_sites(nodes, order, bind, local, parents, position)
    skeleton = Skeleton(names, parents, offsets, [e[0] for e in ends], [e[1] for e in ends],
                        [f"{names[e[0]]}_tip" if e[2] is None else e[2] for e in ends])
    moved = [n for n in order[1:] if rig_parent[n] != parent[n] or not np.allclose(
        np.linalg.inv(bind[parent[n]]) @ bind[n][:, 3], local[n][:, 3], atol=1e-5 * max(skeleton.height(), 1e-9))]
    return Character(path, gltf, buffers, skeleton, order, np.stack([bind[n] for n in order]), above,
                     _overrides(bones, dict(zip(order, names))) or _glued_sides(names, set(hubs.values()), order, parent),
                     kind, moved)


_GLUED = re.compile(r"(?<=[a-z0-9])([LR])(?:_\d+)?$")


def _glued_sides(names: list[str], hubs: set[int], order: list[int], parent: dict[int, int]) -> dict:
    """Overrides for rigs whose side is a capital glued to the name (FootL, Palm2R): each
    side's first foot joint is its ankle, a palm hub (_palms_on_hub) its wrist and the joint the
    hub hangs off its elbow."""
    joints, by_node = {}, dict(zip(order, names))
    for name, n in zip(names, order):
        side = _GLUED.search(name)
        if side and (n in hubs or _FOOT.search(name)):
            key = "left_" if side.group(1) == "L" else "right_"
            if n in hubs:
                joints.setdefault(key + "wrist", name)
                joints.setdefault(key + "elbow", by_node[parent[n]])
            else:
                joints.setdefault(key + "ankle", name)
    return {"joints": joints} if joints else {}


def nodes_below(nodes: list, root: int) -> list[int]:
    """root and every node under it."""
    out, stack = [], [root]
    while stack:
        out.append(stack.pop())
        stack.extend(nodes[out[-1]].children or [])
    return out


def _chain(n: int, parent: dict[int, int]) -> list[int]:
    chain = [n]
    while chain[-1] in parent:
        chain.append(parent[chain[-1]])
    return chain


_FOOT = re.compile(r"foot|ankle", re.I)
_LEG = re.compile(r"leg|thigh|calf|shin|knee", re.I)


def _reattached_feet(order: list[int], names: list[str], bind: dict, parent: dict[int, int]) -> dict[int, int]:
    """Feet of game rigs whose foot bone hangs off the root for IK (Quaternius, the three.js
    robot), each put under the leg joint nearest its bind position that ends a leg chain:
    {foot node: leg node}."""
    by_node = dict(zip(order, names))
    leaves = [n for n in order if not any(parent.get(c) == n for c in order) and _LEG.search(by_node[n])]
    out = {}
    for n in order[1:]:
        if _FOOT.search(by_node[n]) and not any(_LEG.search(by_node.get(a, "")) for a in _chain(n, parent)[1:]) \
                and leaves:
            out[n] = min(leaves, key=lambda leg: np.linalg.norm(bind[leg][:3, 3] - bind[n][:3, 3]))
    return out


def _palms_on_hub(order: list[int], bind: dict, parent: dict[int, int]) -> dict[int, int]:
    """Rigs without a hand bone (the three.js robot: palm bones start together at the wrist, away
    from the forearm joint they hang off): the palms after the first put under the first,
    which then acts as the wrist. {palm node: first palm node}."""
    out = {}
    for n in order:
        children = [c for c in order if parent.get(c) == n]
        at = [bind[c][:3, 3] for c in children]
        if len(children) >= 3:
            gap = np.linalg.norm(at[0] - bind[n][:3, 3])
            together = [c for c, x in zip(children, at) if np.linalg.norm(x - at[0]) < 0.05 * gap]
            if len(together) >= 3:
                out.update({c: together[0] for c in together[1:]})
    return out


def _end_sites(nodes: list, order: list[int], bind: dict, local: dict, parents: list[int],
               position: np.ndarray) -> list[tuple[int, np.ndarray, str | None]]:
    """(joint, offset, name) of each end: a joint's empty leaf child node (Blender's and
    FBX2GLTF's "_end" nodes), else, for a joint with no child joint, a tip half its parent
    bone's length along that bone (a skin's last joint is a bone whose tail glTF does not store)."""
    axis = _bone_axis(order, bind, parents, position)
    ends = []
    for j, n in enumerate(order):
        empty = [c for c in nodes[n].children or [] if c not in order and not nodes[c].children
                 and nodes[c].mesh is None and nodes[c].skin is None and nodes[c].camera is None]
        for c in empty:
            ends.append((j, (bind[n] @ local[c])[:3, 3] - position[j], nodes[c].name))
        if not empty and j not in parents and parents[j] >= 0:
            length = 0.5 * np.linalg.norm(position[j] - position[parents[j]])
            along = bind[n][:3, :3] @ axis if axis is not None else position[j] - position[parents[j]]
            ends.append((j, length * along / max(np.linalg.norm(along), 1e-12), None))
    return ends


def _bone_axis(order: list[int], bind: dict, parents: list[int], position: np.ndarray) -> np.ndarray | None:
    """The joint-frame axis bones point along (Blender's exports: +Y), when at least 80% of the
    joints with one child joint point it at that child; else None."""
    votes = []
    for j, n in enumerate(order):
        children = [c for c, p in enumerate(parents) if p == j]
        if len(children) == 1 and np.linalg.norm(position[children[0]] - position[j]) > 1e-9:
            local = np.linalg.inv(bind[n][:3, :3]) @ (position[children[0]] - position[j])
            local /= np.linalg.norm(local)
            k = int(np.argmax(np.abs(local)))
            votes.append((k, np.sign(local[k])) if abs(local[k]) > 0.9 else None)
    if not votes:
        return None
    best = max(set(votes), key=votes.count)
    if best is None or votes.count(best) < 0.8 * len(votes):
        return None
    return best[1] * np.eye(3)[best[0]]


def _merged(character: Character) -> tuple[gl.GLTF2, BinaryBuffer]:
    """A copy of the document whose buffers are one blob (images moved into it), to append to."""
    gltf = copy.copy(character.gltf)  # what changes is copied: buffer views, images, buffers, animations
    gltf.bufferViews, gltf.images = copy.deepcopy(gltf.bufferViews), copy.deepcopy(gltf.images)
    gltf.animations = list(gltf.animations)
    blob = BinaryBuffer(gltf)
    starts = []
    for i, data in enumerate(character.buffers):
        if data is None:
            raise MotionFileError(character.path, f"buffer {i} has no data")
        starts.append(len(blob.data))
        blob.data += data + b"\0" * (-len(data) % 4)
    for view in gltf.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + starts[view.buffer]
        view.buffer = 0
    for image in gltf.images:
        if image.uri is None:
            continue
        if image.uri.startswith("data:"):
            header, _, payload = image.uri.partition(",")
            data, mime = base64.b64decode(payload), header[5:].split(";")[0]
        else:
            image_path = character.path.parent / image.uri
            try:
                data = image_path.read_bytes()
            except OSError as error:
                raise MotionFileError(character.path, f"image {image.uri!r}: {error.strerror or error}") from None
            mime = mimetypes.guess_type(image.uri)[0] or "image/png"
        offset = len(blob.data)
        blob.data += data + b"\0" * (-len(data) % 4)
        gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=offset, byteLength=len(data)))
        image.uri, image.bufferView, image.mimeType = None, len(gltf.bufferViews) - 1, mime
    gltf.buffers = []
    return gltf, blob


def node_tracks(character: Character, motion: Motion) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """glTF node rotations (T, J, 4) xyzw of the character's joints, and translations (T, 3) of
    the joints whose translation moves ({joint index: track}: the root and Character.moved), for
    a motion on character.skeleton."""
    world, positions = (x.double() for x in motion.world())
    similar = [_similarity(m) for m in character.bind]
    rotation = world @ torch.as_tensor(np.stack([r for r, _ in similar]))       # (T, J, 3, 3) node frames
    scale = [s for _, s in similar]
    index = {n: j for j, n in enumerate(character.nodes)}
    node_parent = {c: index[i] for i in character.nodes for c in character.gltf.nodes[i].children or [] if c in index}
    above_r, above_s = _similarity(character.above)
    frames = len(world)
    quats, translations = torch.empty(frames, len(index), 3, 3, dtype=torch.float64), {}
    for j, n in enumerate(character.nodes):
        p = node_parent.get(n)
        if p is None:
            frame, origin, size = torch.as_tensor(above_r).expand(frames, 3, 3), torch.as_tensor(character.above[:3, 3]), above_s
        else:
            frame, origin, size = rotation[:, p], positions[:, p], scale[p]
        quats[:, j] = frame.transpose(-1, -2) @ rotation[:, j]
        if p is None or n in character.moved:
            translations[j] = ((frame.transpose(-1, -2) @ (positions[:, j] - origin)[..., None])[..., 0] / size).numpy()
    quats = sign_continuous(torch.nn.functional.normalize(rot.matrix_to_quat(quats), dim=-1))
    return roma.quat_wxyz_to_xyzw(quats).numpy(), translations


def joint_transforms(character: Character, motion: Motion) -> torch.Tensor:
    """(T, J, 4, 4) scene transforms of the joint nodes on each frame of a motion on
    character.skeleton (rotation, the bind pose's scale, position)."""
    world, positions = (x.double() for x in motion.world())
    similar = [_similarity(m) for m in character.bind]
    out = torch.zeros(len(world), len(similar), 4, 4, dtype=torch.float64)
    out[..., :3, :3] = world @ torch.as_tensor(np.stack([r * s for r, s in similar]))
    out[..., :3, 3] = positions
    out[..., 3, 3] = 1.0
    return out


def posed_mesh(character: Character, motion: Motion, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The character's triangles posed on every frame of a motion on character.skeleton, as
    glTF viewers draw them: skinned primitives by their skin (sum of w G_j IBM_j v over a
    vertex's joints, JOINTS/WEIGHTS_0 and _1), meshes hung under a joint moving with it, others
    where they stand; morph targets at their default weights. Returns vertices (T, V, 3) float32
    in the scene frame and faces (faces, 3) int64 over all meshes."""
    gltf, path = character.gltf, character.path
    nodes = gltf.nodes
    parent = {c: i for i, node in enumerate(nodes) for c in node.children or []}
    index = {n: j for j, n in enumerate(character.nodes)}
    poses = joint_transforms(character, motion).float()                        # (T, J, 4, 4)
    frames = len(poses)
    vertices, faces, count = [], [], 0
    for n, node in enumerate(nodes):
        if node.mesh is None:
            continue
        for primitive in gltf.meshes[node.mesh].primitives:
            if primitive.mode not in (None, gl.TRIANGLES) or primitive.attributes.POSITION is None:
                continue
            points = accessor_values(path, gltf, character.buffers, primitive.attributes.POSITION)
            homogeneous = torch.from_numpy(np.concatenate([points, np.ones((len(points), 1))], 1)).float()
            triangles = (accessor_values(path, gltf, character.buffers, primitive.indices).reshape(-1, 3)
                         if primitive.indices is not None else np.arange(len(points)).reshape(-1, 3))
            if node.skin is not None:
                skin = gltf.skins[node.skin]
                inverse = torch.from_numpy(accessor_values(path, gltf, character.buffers, skin.inverseBindMatrices)
                                           .reshape(-1, 4, 4).transpose(0, 2, 1).copy()).float()
                matrices = poses[:, [index[j] for j in skin.joints]] @ inverse      # (T, Jskin, 4, 4)
                influences = [(getattr(primitive.attributes, f"JOINTS_{k}"), getattr(primitive.attributes, f"WEIGHTS_{k}"))
                              for k in (0, 1) if getattr(primitive.attributes, f"JOINTS_{k}", None) is not None]
                joints = torch.from_numpy(np.concatenate([accessor_values(path, gltf, character.buffers, a)
                                                          for a, _ in influences], 1).astype(np.int64))
                weights = torch.from_numpy(np.concatenate([accessor_values(path, gltf, character.buffers, w)
                                                           for _, w in influences], 1)).float()
                weights = weights / weights.sum(1, keepdim=True).clamp_min(1e-12)
                posed = torch.zeros(frames, len(points), 3)
                for start in range(0, frames, chunk):
                    m = matrices[start:start + chunk]
                    for k in range(joints.shape[1]):
                        moved = (m[:, joints[:, k]] @ homogeneous[None, :, :, None])[..., :3, 0]
                        posed[start:start + chunk] += weights[None, :, k, None] * moved
            else:
                chain, above = [], n
                while above is not None and above not in index:
                    chain.append(above)
                    above = parent.get(above)
                local = torch.eye(4)
                for a in reversed(chain):
                    local = local @ torch.from_numpy(_matrix(*node_transform(path, nodes[a], a))).float()
                carry = poses[:, index[above]] @ local if above is not None else local.expand(frames, 4, 4)
                posed = (carry[:, None] @ homogeneous[None, :, :, None])[..., :3, 0]
            vertices.append(posed.numpy())
            faces.append(triangles.astype(np.int64) + count)
            count += len(points)
    if not vertices:
        return np.zeros((frames, 0, 3), np.float32), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices, 1), np.concatenate(faces)


def write_character(character: Character, motion: Motion, path: str | Path, name: str | None = None) -> None:
    """Write the character with the motion (on character.skeleton: same joint names) as its
    first animation, named name (default the motion's name). path: .glb, .vrm (binary) or .gltf
    (JSON); .fbx through Blender (humotion[fbx]). Raises ValueError for a motion on another
    skeleton or another suffix."""
    path = Path(path)
    suffix = base_suffix(path)
    if suffix == ".fbx":
        with tempfile.TemporaryDirectory() as folder:
            glb = Path(folder) / f"{path.stem}.glb"
            write_character(character, motion, glb, name)
            _blender_convert(glb, path, motion.fps)
        return
    if suffix not in (".glb", ".gltf", ".vrm"):
        raise ValueError(f"a character is written as .glb, .gltf, .vrm or .fbx, not {suffix!r} ({path})")
    if tuple(motion.skeleton.names) != tuple(character.skeleton.names):
        raise ValueError(f"the motion is on another skeleton ({motion.skeleton.num_joints} joints) than the "
                         f"character's ({character.skeleton.num_joints} joints)")
    quats, translations = node_tracks(character, motion)
    gltf, blob = _merged(character)
    title = name or motion.name or "humotion"
    animation = gl.Animation(name=title, extras={"fps": float(motion.fps), "generator": "humotion"})
    times = blob.add((np.arange(motion.num_frames) / motion.fps).astype(np.float32), "SCALAR", bounds=True)

    def channel(node: int, target: str, values: np.ndarray) -> None:
        output = blob.add(np.ascontiguousarray(values, dtype=np.float32), "VEC4" if values.shape[1] == 4 else "VEC3")
        animation.samplers.append(gl.AnimationSampler(input=times, output=output, interpolation=gl.ANIM_LINEAR))
        animation.channels.append(gl.AnimationChannel(sampler=len(animation.samplers) - 1,
                                                      target=gl.AnimationChannelTarget(node=node, path=target)))

    for j, node in enumerate(character.nodes):
        channel(node, gl.ROTATION, quats[:, j])
        if j in translations:
            channel(node, gl.TRANSLATION, translations[j])
    gltf.animations.insert(0, animation)
    data = bytes(blob.data)
    if suffix == ".gltf":
        gltf.buffers = [gl.Buffer(byteLength=len(data),
                                  uri="data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii"))]
        payload = gltf.gltf_to_json().encode("utf-8")
    else:
        gltf.buffers = [gl.Buffer(byteLength=len(data))]
        gltf.set_binary_blob(data)
        payload = b"".join(gltf.save_to_bytes())
    write_atomic(path, payload)


# ---------------------------------------------------------------------------------------------
# FBX through Blender (bpy)
# ---------------------------------------------------------------------------------------------
def _bpy():
    try:
        import bpy
    except ImportError:
        return None
    return bpy


def _blender_convert(source: Path, target: Path, fps: float | None = None) -> None:
    """Convert between FBX and glTF with Blender's own add-ons (an empty scene each time); to
    FBX, the scene runs at fps (Blender's default 24 otherwise) over the first animation's frames.
    Blender's own printing goes to a log; its last line names a failure."""
    fbx = source if base_suffix(source) == ".fbx" else target
    with tempfile.TemporaryFile("w+") as log_file, _quiet(log_file):
        bpy = _bpy()  # importing it prints a NumPy 2 notice from a module it does not need
        if bpy is None:
            raise MotionFileError(fbx, "FBX needs Blender's Python module: pip install 'humotion[fbx]'")
        try:
            bpy.ops.wm.read_factory_settings(use_empty=True)
            scene = bpy.context.scene
            if fps:
                scene.render.fps, scene.render.fps_base = round(fps), round(fps) / fps
            if base_suffix(source) == ".fbx":
                bpy.ops.import_scene.fbx(filepath=str(source))
            else:
                bpy.ops.import_scene.gltf(filepath=str(source))
            actions = [o.animation_data.action for o in scene.objects if o.animation_data and o.animation_data.action]
            if actions:
                scene.frame_start, scene.frame_end = (int(round(x)) for x in actions[0].frame_range)
            if base_suffix(target) == ".fbx":
                bpy.ops.export_scene.fbx(filepath=str(target), add_leaf_bones=False, bake_anim=True,
                                         bake_anim_use_all_actions=False, bake_anim_use_nla_strips=False)
            else:
                bpy.ops.export_scene.gltf(filepath=str(target), export_format="GLB", export_animations=True)
        except RuntimeError as error:  # bpy.ops report failures as RuntimeError
            raise MotionFileError(fbx, f"Blender could not convert it ({str(error).strip().splitlines()[-1]})") from None


@contextlib.contextmanager
def _quiet(log_file):
    """Blender prints to the process's stdout and stderr (C code) and to Python's: all to log_file."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        os.dup2(log_file.fileno(), 1)
        os.dup2(log_file.fileno(), 2)
        with contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def _read_fbx(path: Path) -> Character:
    if not path.is_file():
        raise MotionFileError(path, "cannot read the file (no such file)")
    with tempfile.TemporaryDirectory() as folder:
        glb = Path(folder) / f"{path.stem}.glb"
        _blender_convert(path, glb)
        character = read_character(glb)  # reads every byte it needs before the folder goes
    character.path, character.kind = path, "FBX"
    return character


__all__ = ["Character", "read_character", "write_character", "node_tracks", "humanoid_bones", "SUFFIXES"]
