"""One headset frame -> one body pose, as a pure function of tensors: what SparseTracker runs per
frame, in PyTorch or exported to ONNX and run by ONNX Runtime (lower latency; the same file runs
in game engines: Unity Sentis, Unreal NNE, or any ONNX runtime).

Inputs (float32; metres, humotion's world frame, see humotion.sparse.recording):
    rotations (3, 3, 3), positions (3, 3): head (eyes), left and right wrist; visible (2,) 0/1
    previous_rotations, previous_positions, previous_visible: the same on the previous frame
        (on a stream's first frame: the current ones)
    offsets (22, 3): the user's canonical skeleton (humotion.canonical.canonical_skeleton(height))
    eye (3,): eye position in the head joint's frame (humotion.sparse.signals.eye_offset)
    t (1,) int64, origin (1, 2), hidden (1, 5, H), stae (1, 5, H), pose (1, 22, 6), root (1, 3),
        root_rotation (1, 3, 3), delta (1, 3): the network's state (SparsePoser.initial_state)
Outputs: local joint rotations (22, 4) wxyz (joint 0 global), root position (3,), world joint
positions (22, 3), then the next state's tensors in the order above (``STATE_FIELDS``).

    humotion export sparse -o tracker.onnx          # the shipped weights as ONNX
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
from torch import nn

from humotion import rotations as rot
from humotion.atomic import atomic_file
from humotion.canonical import JOINTS, PARENTS, canonical_skeleton
from humotion.skeleton import forward_kinematics_by_level
from humotion.sparse import signals as sg
from humotion.sparse.model import SparsePoser, SparseState

log = logging.getLogger(__name__)

SHIPPED_DIR = Path(__file__).resolve().parents[1] / "assets" / "sparse"
SHIPPED_ONNX = SHIPPED_DIR / "sparse_poser.onnx"     # the default network's; each shipped .pt has its .onnx
STATE_FIELDS = tuple(f.name for f in fields(SparseState))
INPUTS = ("rotations", "positions", "visible", "previous_rotations", "previous_positions", "previous_visible",
          "offsets", "eye") + STATE_FIELDS
OUTPUTS = ("local_rotations", "root_position", "joint_positions") + tuple(f"next_{name}" for name in STATE_FIELDS)


def head_eyes(world_rotations: torch.Tensor, world_positions: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """(..., 3) eye positions from canonical-body forward kinematics: world_rotations
    (..., 22, 3, 3), world_positions (..., 22, 3) metres, eye (3,) offset in the head frame."""
    head = JOINTS.index("head")
    return world_positions[..., head, :] + (world_rotations[..., head, :, :] @ eye.to(world_positions.dtype)[:, None])[..., 0]


class FrameGraph(nn.Module):
    """SparseTracker's per-frame computation (module docstring): signals, the network, forward
    kinematics, the root moved so the eyes meet the headset when anchor_head. Written for a small
    ONNX graph (ONNX Runtime's time goes mostly on per-node overhead): one frame's signals
    (signals.frame_signals), the network's per-frame step (SparsePoser.advance), forward
    kinematics depth by depth (humotion.skeleton.forward_kinematics_by_level), quaternions by one
    matrix product."""

    def __init__(self, model: SparsePoser, anchor_head: bool = True):
        super().__init__()
        self.model, self.anchor_head = model, anchor_head

    def forward(self, rotations, positions, visible, previous_rotations, previous_positions, previous_visible,
                offsets, eye, *state):
        state = SparseState(*state)
        origin = sg.ground_point(state.origin)                                         # (1, 3)
        x = sg.frame_signals(rotations, positions - origin, visible,
                             previous_rotations, previous_positions - origin, previous_visible)
        out, state = self.model.advance(x[None], visible[None], state)
        local, root = out.rotations[0], out.root_positions[0] + origin[0]                  # (22, 3, 3), (3,)
        world_r, world_p = forward_kinematics_by_level(local, root, offsets, PARENTS)        # (22, 3, 3), (22, 3)
        if self.anchor_head:
            shift = positions[0] - head_eyes(world_r, world_p, eye)
            root, world_p = root + shift, world_p + shift
        return (rot.matrix_to_quat_in_one_product(local), root, world_p) + astuple_shallow(state)


def astuple_shallow(state: SparseState) -> tuple:
    """The state's tensors in STATE_FIELDS order (dataclasses.astuple would deep-copy them)."""
    return tuple(getattr(state, name) for name in STATE_FIELDS)


def state_is_sound(state: tuple, head_position, max_root_distance: float) -> bool:
    """Whether a stream's network state (STATE_FIELDS order; tensors or arrays, batch of one) is
    usable: finite, and the internal root (pelvis; recentred, so origin's ground point added)
    within max_root_distance metres of head_position (3,), the eyes. A state that fails has been
    driven out of anything a body can be (a glitch reaching the network, or numerical blow-up)
    and is re-initialised by the tracker rather than left to produce NaN. Sums stand in for
    element-wise checks (a NaN or infinity anywhere makes the sum non-finite): this runs on
    every frame."""
    fields = dict(zip(STATE_FIELDS, state))
    for name in ("hidden", "stae", "pose", "delta"):
        if not math.isfinite(float(fields[name].sum())):
            return False
    origin, root = fields["origin"].reshape(-1).tolist(), fields["root"].reshape(-1).tolist()
    head = [float(v) for v in head_position]
    distance = math.dist((root[0] + origin[0], root[1], root[2] + origin[1]), head)
    return distance <= max_root_distance     # False for NaN too


def example_inputs(model: SparsePoser) -> tuple:
    """A valid input tuple (a standing user's first frame) for tracing and tests."""
    rotations = torch.eye(3).expand(3, 3, 3).contiguous()
    positions = torch.tensor([[0.0, 1.6, 0.0], [0.3, 1.0, 0.2], [-0.3, 1.0, 0.2]])
    visible = torch.ones(2)
    skeleton = canonical_skeleton()
    offsets = skeleton.offsets
    state = model.initial_state(positions[None, 0, [0, 2]])
    previous = (rotations.clone(), positions.clone(), visible.clone())   # distinct tensors: aliased inputs get merged
    return (rotations, positions, visible, *previous, offsets, sg.eye_offset(skeleton)) + astuple_shallow(state)


def export_onnx(model: SparsePoser, path: str | Path, anchor_head: bool = True) -> Path:
    """Write the frame function of model to an ONNX file (needs the onnx and onnxscript packages;
    about half a minute on a CPU), its weights digest and anchoring in the file's metadata."""
    import onnx

    path = Path(path)
    graph = FrameGraph(model, anchor_head).eval().requires_grad_(False)
    with torch.no_grad():
        program = torch.onnx.export(graph, example_inputs(model), input_names=list(INPUTS),
                                    output_names=list(OUTPUTS), dynamo=True, verbose=False)
    proto = program.model_proto
    for node in proto.graph.node:      # the exporter's stack traces (paths on this machine): not needed to run
        del node.metadata_props[:]
    for key, value in (("weights_digest", weights_digest(model)), ("anchor_head", str(anchor_head)),
                       ("fps", str(getattr(model, "fps", 30.0)))):
        proto.metadata_props.add(key=key, value=value)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as file:     # never a half-written file under the final name
        onnx.save(proto, file)
    return path


def onnx_file(model: SparsePoser, anchor_head: bool = True, export: bool = True) -> Path | None:
    """An ONNX file of model's frame function: one shipped beside the shipped weights when it
    matches, else one in the cache folder ($HUMOTION_CACHE or ~/.cache/humotion), exported once
    when export is True (logged at INFO: it takes about half a minute; else None when there is
    none yet)."""
    from humotion.data.cache import default_cache_dir

    digest = weights_digest(model)
    for shipped in sorted(SHIPPED_DIR.glob("*.onnx")):
        if onnx_matches(shipped, digest, anchor_head):
            return shipped
    cached = default_cache_dir() / "sparse" / f"frame-{digest}-{'anchored' if anchor_head else 'free'}.onnx"
    if not cached.is_file():
        if not export:
            return None
        log.info("exporting the sparse-tracking frame function to %s (once, about half a minute)", cached)
        export_onnx(model, cached, anchor_head)
    return cached


def onnx_matches(path: Path, digest: str, anchor_head: bool) -> bool:
    """Whether path is an ONNX export of the weights with this digest and anchoring."""
    if not path.is_file():
        return False
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    return meta.get("weights_digest") == digest and meta.get("anchor_head") == str(anchor_head)


def weights_digest(model: SparsePoser) -> str:
    """A short hex digest of the model's configuration and weights (names ONNX files in caches).
    Fields that shape training only (SparseConfig.TRAINING_ONLY) are left out, and the rest
    are written as the dataclass repr writes them, so a file's digest does not depend on them."""
    fields = {k: v for k, v in vars(model.config).items() if k not in model.config.TRAINING_ONLY}
    digest = hashlib.sha256(f"SparseConfig({', '.join(f'{k}={v!r}' for k, v in fields.items())})".encode())
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().numpy().tobytes())
    return digest.hexdigest()[:16]


class OnnxStream:
    """The frame function run by ONNX Runtime on one CPU thread, one stream at a time.

    Inputs and outputs live in numpy buffers bound to the session once (ONNX Runtime's I/O
    binding), so a frame converts nothing: two bindings alternate, each reading the frame and
    state buffers the other writes (bench/sparse_floor.py measures what that saves over
    session.run with a dict of arrays). ONNX Runtime's MatMulAddFusion is switched off: it turns
    each batched linear layer into a Gemm between two Reshapes, which for one frame saves nothing.
    """

    def __init__(self, path: str | Path, threads: int = 1):
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = threads
        self.session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"],
                                                    disabled_optimizers=["MatMulAddFusion"])
        self._bindings = None

    def start(self, offsets: np.ndarray, eye: np.ndarray, state: tuple) -> None:
        """Begin a stream: offsets (22, 3) and eye (3,) of the user's body (see INPUTS), state the
        network's initial state (SparsePoser.initial_state, tensors or arrays)."""
        from onnxruntime import OrtValue

        body = [np.ascontiguousarray(value, np.float32) for value in (offsets, eye)]
        states = [[np.array(value.numpy() if isinstance(value, torch.Tensor) else value) for value in state] for _ in range(2)]
        frames = [[np.zeros((3, 3, 3), np.float32), np.zeros((3, 3), np.float32), np.zeros(2, np.float32)]
                  for _ in range(2)]
        outputs = [np.zeros((22, 4), np.float32), np.zeros(3, np.float32), np.zeros((22, 3), np.float32)]
        self._body_and_states = (body, states)    # bound arrays must outlive the bindings (frames, outputs: below)
        self._bindings = []
        for now in (0, 1):
            binding = self.session.io_binding()
            inputs = frames[now] + frames[1 - now] + body + states[now]
            for name, array in zip(INPUTS, inputs):
                binding.bind_ortvalue_input(name, OrtValue.ortvalue_from_numpy(array))
            for name, array in zip(OUTPUTS, outputs + states[1 - now]):
                binding.bind_ortvalue_output(name, OrtValue.ortvalue_from_numpy(array))
            self._bindings.append(binding)
        self._frames, self._outputs, self._now, self._first = frames, outputs, 0, True

    def __call__(self, rotations: np.ndarray, positions: np.ndarray, visible: np.ndarray) -> tuple:
        """One frame (INPUTS' rotations (3, 3, 3), positions (3, 3), visible (2,)) -> copies of
        local_rotations (22, 4), root_position (3,), joint_positions (22, 3)."""
        if self._bindings is None:
            raise RuntimeError("call start() before the first frame")
        now = self._now
        for previous, current, value in zip(self._frames[1 - now], self._frames[now], (rotations, positions, visible)):
            current[...] = value
            if self._first:            # a stream's first frame is its own previous frame
                previous[...] = value
        self.session.run_with_iobinding(self._bindings[now])
        self._now, self._first = 1 - now, False
        return tuple(output.copy() for output in self._outputs)

    def state(self) -> tuple:
        """The network state after the last frame (arrays in STATE_FIELDS order, not copies)."""
        if self._bindings is None:
            raise RuntimeError("call start() before the first frame")
        return tuple(self._body_and_states[1][self._now])


class TorchStream:
    """FrameGraph run like OnnxStream (arrays or tensors in, tensors out)."""

    def __init__(self, model: SparsePoser, anchor_head: bool = True):
        self.graph = FrameGraph(model, anchor_head)
        self._state = None

    def start(self, offsets, eye, state: tuple) -> None:
        self._body = tuple(torch.as_tensor(value, dtype=torch.float32) for value in (offsets, eye))
        self._state, self._previous = tuple(torch.as_tensor(value) for value in state), None

    @torch.no_grad()
    def __call__(self, rotations, positions, visible) -> tuple:
        if self._state is None:
            raise RuntimeError("call start() before the first frame")
        frame = tuple(torch.as_tensor(value) for value in (rotations, positions, visible))
        local, root, world, *state = self.graph(*frame, *(self._previous or frame), *self._body, *self._state)
        self._previous, self._state = frame, tuple(state)
        return local, root, world

    def state(self) -> tuple:
        """The network state after the last frame (tensors in STATE_FIELDS order)."""
        if self._state is None:
            raise RuntimeError("call start() before the first frame")
        return self._state
