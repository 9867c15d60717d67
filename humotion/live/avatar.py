"""The live page's avatar: a body of the learned body model (``humotion body``) as a skinned glTF,
and the table with which the page drives its 76-bone rig from the 22 canonical joint rotations
the server streams.

The table is the retargeting of humotion.body.posing.canonical_to_rig written out once: with
G_c a canonical joint's world rotation (identity: the canonical T-pose), a rig bone driven by
canonical joint c (humotion.body.posing.CANONICAL_TO_RIG, the clavicles excepted: HELD_AT_REST)
has the world rotation G_c S_j, any other bone (twist bones, fingers, eyes) its parent's; S_j is
the bone's world rotation when the canonical body stands in its T-pose (the rest alignment that
canonical_to_rig computes: the rig's A-pose turned onto the T-pose). A clavicle has its parent's
(the chest's) world rotation A_p times a rise about a fixed axis of CLAVICLE_RISE times the upper
arm's elevation above the chest's horizontal, when positive (the arm: G_shoulder times the
canonical shoulder-to-elbow rest vector, in the chest's axes A_p^T), as canonical_to_rig raises
it. The page takes each bone's local rotation from those world rotations.

All in humotion's axes (metres, Y up, facing +Z); the page turns the whole avatar into its
connection's convention.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS

DEFAULT_HEIGHT = 1.7
"""Standing height in metres of the body made when the server is given none."""


@dataclass
class Avatar:
    """A body for the live page: glb, the skinned body (glTF binary, rest pose, 4 joints per
    vertex, no morph targets); table, the JSON-ready retargeting table (module docstring):
    {"height": metres, "bones": rig bone names, "parents": their parent indices, "drivers":
    canonical joint index driving each bone or -1, "rest": S_j as wxyz quaternions (J, 4),
    "root": the rig root's rest position (3,) metres, "clavicles": per held clavicle {"bone": its
    index, "shoulder": the canonical shoulder's index, "aim": the canonical shoulder-to-elbow rest
    vector (3,), "axis": the unit axis of its rise in its parent's frame (3,), "rise": the share of
    the arm's elevation it rises by}}."""

    glb: bytes
    table: dict


def make_avatar(height: float | None = None, path: str | Path | None = None) -> Avatar:
    """The avatar of a body GLB written by ``humotion body`` (path: its shape is read back from
    the file's humotion_body extras, so its rig can be retargeted), else a new body of this
    standing height (metres; DEFAULT_HEIGHT when None) and the typical weight at that height.
    ValueError naming the problem for a file that is not such a body."""
    from humotion.body.export import body_gltf, body_measurements, rest_body
    from humotion.body.model import load_body_model
    from humotion.io.gltf import write_gltf

    if path is not None:
        glb = Path(path).read_bytes()
        facts = _body_facts(glb, str(path))
        model = load_body_model(facts["resolution"])
        shape = torch.tensor([facts["shape_latent"]], dtype=torch.float32)
        body = rest_body(model, shape)
    else:
        model = load_body_model("low")
        body = rest_body(model, model.shape_from_measurements(*body_measurements(height or DEFAULT_HEIGHT, None)))
        rest = torch.eye(3).expand(1, model.num_joints, 3, 3)
        rig_motion, mesh = body_gltf(body, rest, body.joints[:1], 30.0, "live", influences=4, correctives=False)
        with tempfile.TemporaryDirectory() as folder:
            out = Path(folder) / "body.glb"
            write_gltf(rig_motion, out, mesh=mesh)
            glb = out.read_bytes()
    return Avatar(glb, retarget_table(body))


def retarget_table(body) -> dict:
    """The page's retargeting table (Avatar.table) of a humotion.body.export.RestBody."""
    from humotion.body.posing import CANONICAL_TO_RIG, CLAVICLE_RISE, HELD_AT_REST, canonical_to_rig
    from humotion.canonical import canonical_skeleton
    from humotion.skeleton import forward_kinematics

    names, parents = list(body.model.joint_names), list(body.model.parents)
    t_pose = torch.eye(3, dtype=torch.float64).expand(1, len(JOINTS), 3, 3)
    local = canonical_to_rig(t_pose, body.vertices.double(), body.joints.double(), names, parents)
    world, _ = forward_kinematics(local[0], torch.zeros(3, dtype=torch.float64),
                                  np.zeros((len(names), 3)), parents)
    drivers = [-1] * len(names)
    for joint, bone in CANONICAL_TO_RIG.items():
        if joint not in HELD_AT_REST:
            drivers[names.index(bone)] = JOINTS.index(joint)
    template = canonical_skeleton().rest_positions(torch.float64).numpy()
    joints = body.joints.double().numpy()
    clavicles = []
    for collar in HELD_AT_REST:              # as humotion.body.posing._clavicle_rise
        bone, shoulder = names.index(CANONICAL_TO_RIG[collar]), JOINTS.index(collar.replace("collar", "shoulder"))
        outward = joints[names.index(CANONICAL_TO_RIG[collar.replace("collar", "shoulder")])] - joints[bone]
        axis = np.cross(outward, [0.0, 1.0, 0.0])
        clavicles.append({"bone": bone, "shoulder": shoulder,
                          "aim": np.round(template[JOINTS.index(collar.replace("collar", "elbow"))] - template[shoulder], 7).tolist(),
                          "axis": np.round(axis / np.linalg.norm(axis), 7).tolist(), "rise": CLAVICLE_RISE})
    return {"height": round(float(body.measurements()["height"]), 4), "bones": names, "parents": parents,
            "drivers": drivers, "rest": np.round(rot.matrix_to_quat(world).numpy(), 7).tolist(),
            "root": np.round(body.joints[0].double().numpy(), 6).tolist(), "clavicles": clavicles}


def _body_facts(glb: bytes, name: str) -> dict:
    """The humotion_body extras of a body GLB (resolution, shape_latent, ...); ValueError otherwise."""
    import struct

    if len(glb) < 20 or glb[:4] != b"glTF":
        raise ValueError(f"{name}: not a binary glTF (.glb) file")
    length, kind = struct.unpack_from("<II", glb, 12)
    try:
        document = json.loads(glb[20:20 + length]) if kind == 0x4E4F534A else {}
    except ValueError:
        document = {}
    for mesh in document.get("meshes", []):
        facts = (mesh.get("extras") or {}).get("humotion_body")
        if isinstance(facts, dict) and "shape_latent" in facts and facts.get("resolution") in ("low", "full"):
            return facts
    raise ValueError(f"{name}: not a body written by `humotion body` (no humotion_body facts in its meshes' extras)")
