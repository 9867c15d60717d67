"""After the network: the arms solved so the wrists meet the tracked hands, the feet kept on the
floor and locked while planted. Pure numpy functions of joint positions and rotations; the same
code runs one frame (SparseTracker.update: a batch of one, the state carried between calls) and a
whole recording (SparseTracker.track, :func:`solve_body`: the frame-to-frame state machines loop
over frames, the geometry runs batched over all of them).

Dimension letters: F frames, J = 22 canonical joints. Units: metres, seconds; world frame Y up.

Stages of :func:`solve_frames`, per frame:

1. Floor: a height (metres, world Y) taken from the stream's first standing frames
   (:func:`floor_from_head`: the highest eye height over the first second, less the body's
   standing eye height), or given.
2. Root lift: when a hip would sit so low that its foot cannot be above the floor (a person lying
   down, with the body posed upright below the headset), the whole body is raised.
3. Feet: a foot is in contact when its sole is near the floor and its ball moves slowly
   (:func:`foot_contacts`, the same rule the metrics use); a contact locks the ball where it
   first touched, and a release blends it back to the network's over ``release_s``. The ball
   and ankle are kept above the floor on every frame. Hip-knee-ankle two-bone IK
   (:func:`two_bone_ik`) places the ankle; the foot keeps the network's orientation.
4. Arms: a visible hand's wrist is reached by shoulder-elbow-wrist two-bone IK, with the
   elbow's swivel taken from the network's elbow (the pole). The wrist takes the controller's
   orientation. A hand entering or leaving the view is blended in or out at a limited speed of
   the correction (``blend_speed``), so the wrist does not jump.

Bone lengths are the skeleton's (the user-scaled canonical body, or a calibrated one).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from humotion import rotations as rot
from humotion.canonical import JOINTS, PARENTS
from humotion.motion import Motion
from humotion.skeleton import Skeleton

ARMS = tuple(tuple(JOINTS.index(f"{s}_{j}") for j in ("shoulder", "elbow", "wrist")) for s in ("left", "right"))
LEGS = tuple(tuple(JOINTS.index(f"{s}_{j}") for j in ("hip", "knee", "ankle")) for s in ("left", "right"))
BALLS = tuple(JOINTS.index(f"{s}_foot") for s in ("left", "right"))
ANKLES = tuple(leg[2] for leg in LEGS)
PELVIS, HEAD = JOINTS.index("pelvis"), JOINTS.index("head")
_PARENTS = np.array([max(p, 0) for p in PARENTS])


@dataclass(frozen=True)
class SolveSettings:
    """What the solve does and its thresholds (metres, seconds)."""

    arms: bool = True
    """Solve the arms to the visible hands."""
    feet: bool = True
    """Lock planted feet and keep the feet above the floor."""
    hand_orientation: bool = True
    """Give the wrist the tracked hand's orientation."""
    blend_speed: float = 1.0
    """m/s: the most a hand's correction changes per second while it blends in or out."""
    contact_height: float = 0.06
    """m: a sole at most this far above the floor can be in contact."""
    contact_speed: float = 0.3
    """m/s: a ball moving horizontally slower than this can be in contact."""
    release_s: float = 0.2
    """s: a released foot returns to the network's place over this time."""
    floor_window_s: float = 1.0
    """s: the stream's first seconds in which the floor is taken (the user stands)."""


@dataclass
class SolveState:
    """What the solve carries from frame to frame of one stream (numpy arrays, two hands / feet).

    correction (2, 3): each hand's wrist offset from the network's; hand_locked (2,): the offset
    follows the target exactly (blending done). previous_ball (2, 3) the network's balls on the
    previous frame (None on the first); started: a frame was solved (a hand seen on the stream's
    first frame is reached at once, with nothing to blend from); locked (2,), lock (2, 3) where a planted ball is held;
    release (2, 3) the offset being blended out after a release, release_left (2,) its frames."""

    correction: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    hand_locked: np.ndarray = field(default_factory=lambda: np.zeros(2, bool))
    previous_ball: np.ndarray | None = None
    locked: np.ndarray = field(default_factory=lambda: np.zeros(2, bool))
    lock: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    release: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    release_left: np.ndarray = field(default_factory=lambda: np.zeros(2, int))
    started: bool = False


# -- geometry ---------------------------------------------------------------------------------
def _normalise(v: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, eps), n[..., 0]


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the smallest rotation turning direction a (..., 3) onto direction b (..., 3)
    (Rodrigues' formula); opposite directions turn half a turn about an axis normal to a."""
    a, _ = _normalise(a)
    b, _ = _normalise(b)
    axis = np.cross(a, b)
    cos = np.sum(a * b, -1)
    k = _skew(axis)
    turn = np.eye(3) + k + (k @ k) / np.maximum(1.0 + cos, 1e-12)[..., None, None]
    opposite = cos < -1 + 1e-9
    if np.any(opposite):       # half a turn about any axis n normal to a: 2 n n^T - I
        other = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        n, _ = _normalise(np.cross(a, other))
        turn = np.where(opposite[..., None, None], 2 * n[..., :, None] * n[..., None, :] - np.eye(3), turn)
    return turn


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the cross-product matrix of vectors (..., 3)."""
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return k


def two_bone_ik(root: np.ndarray, target: np.ndarray, pole: np.ndarray, upper: np.ndarray,
                lower: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The middle and end joints of a two-bone chain reaching for a target.

    Args:
        root (..., 3): the chain's first joint (shoulder, hip), metres; it stays.
        target (..., 3): where the end joint (wrist, ankle) should be.
        pole (..., 3): a direction from the root, the side the middle joint (elbow, knee) bends to
            (only its part normal to the root-target line counts; the swivel).
        upper, lower (...,): bone lengths root-middle and middle-end, metres.
    Returns:
        (middle (..., 3), end (..., 3)): end = target when it is within reach; else the chain
        points at the target, straight (too far) or folded (too near).
    """
    upper, lower = np.asarray(upper, float), np.asarray(lower, float)
    u, distance = _normalise(target - root)
    reach = np.clip(distance, np.abs(upper - lower) + 1e-6, upper + lower)
    along = (upper**2 - lower**2 + reach**2) / (2 * reach)
    height = np.sqrt(np.maximum(upper**2 - along**2, 0.0))
    side = pole - np.sum(pole * u, -1, keepdims=True) * u
    side, size = _normalise(side)
    if np.any(size < 1e-9):     # pole along the line: any normal
        other = np.where(np.abs(u[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        side = np.where((size < 1e-9)[..., None], _normalise(np.cross(u, other))[0], side)
    middle = root + along[..., None] * u + height[..., None] * side
    return middle, root + reach[..., None] * u


def _rotvec(m: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle of rotation matrices (..., 3, 3), angles below pi."""
    cos = np.clip((np.trace(m, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    w = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)
    sin = np.sin(angle)
    return w * np.where(sin > 1e-6, angle / np.maximum(2 * sin, 1e-12), 0.5)[..., None]


def _matrix(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of axis-angle vectors (..., 3)."""
    axis, angle = _normalise(v)
    k = _skew(axis)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def blend_rotations(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations from a (weight 0) to b (weight 1) along the shortest arc; weight (...)."""
    return a @ _matrix(_rotvec(np.swapaxes(a, -1, -2) @ b) * np.asarray(weight)[..., None])


def _bend_chain(world_r, world_p, chain, middle, end):
    """Turn the chain's first two bones onto new middle and end positions (minimal turns, the
    rest of each joint's frame carried along); the end joint's rotation turns with its parent.
    world_r (F, J, 3, 3), world_p (F, J, 3) changed in place."""
    a, b, c = chain
    turn_a = rotation_between(world_p[:, b] - world_p[:, a], middle - world_p[:, a])
    lower = np.einsum("fij,fj->fi", turn_a, world_p[:, c] - world_p[:, b])
    turn_b = rotation_between(lower, end - middle) @ turn_a
    world_r[:, a] = turn_a @ world_r[:, a]
    world_r[:, b] = turn_b @ world_r[:, b]
    world_r[:, c] = turn_b @ world_r[:, c]
    world_p[:, b], world_p[:, c] = middle, end


def _pole(world_p, chain, fallback):
    """The network's bend direction of a chain (its middle joint's offset from the root-end line),
    with a small default direction added so a straight limb still has a side (F, 3)."""
    a, b, c = chain
    line, _ = _normalise(world_p[:, c] - world_p[:, a])
    bend = world_p[:, b] - world_p[:, a]
    bend = bend - np.sum(bend * line, -1, keepdims=True) * line
    return bend + 0.02 * fallback


def _lengths(offsets: np.ndarray, chain) -> tuple[float, float]:
    return float(np.linalg.norm(offsets[chain[1]])), float(np.linalg.norm(offsets[chain[2]]))


# -- the body's own heights -------------------------------------------------------------------
def foot_clearance(skeleton: Skeleton) -> np.ndarray:
    """(2,) heights of the ankle and of the ball (foot joint) above the sole (the toe tips) when
    standing, metres, from the skeleton's rest pose."""
    rest = skeleton.rest_positions()
    toe = skeleton.rest_end_site_positions()[skeleton.end_site_names.index("left_toe")][1]
    return np.array([rest[ANKLES[0], 1] - toe, rest[BALLS[0], 1] - toe])


def standing_eye_height(skeleton: Skeleton, eye: np.ndarray) -> float:
    """Eye height above the sole of the skeleton standing in its rest pose (eye: (3,) the eyes in
    the head joint's frame, humotion.sparse.signals.eye_offset), metres."""
    rest = skeleton.rest_positions()
    toe = skeleton.rest_end_site_positions()[skeleton.end_site_names.index("left_toe")][1]
    return float(rest[HEAD, 1] + np.asarray(eye)[1] - toe)


def floor_from_head(head_heights: np.ndarray, skeleton: Skeleton, eye: np.ndarray, fps: float,
                    window_s: float = 1.0) -> float:
    """The floor height (metres, world Y) from the stream's first standing frames: the highest
    eye height (head_heights (F,) metres) in the first window_s seconds, less the body's standing
    eye height. Assumes the user stands up straight at some moment of that window."""
    first = np.asarray(head_heights)[: max(1, int(round(window_s * fps)))]
    return float(np.max(first)) - standing_eye_height(skeleton, eye)


def sole_heights(world_p: np.ndarray, clearance: np.ndarray, floor: float) -> np.ndarray:
    """(..., F, 2) height above the floor of each foot's sole (left, right): the lower of ankle and
    ball, each less its standing clearance. world_p (..., F, J, 3) metres; clearance (2,)
    (:func:`foot_clearance`); floor metres."""
    ankle = world_p[..., ANKLES, 1] - clearance[0]
    ball = world_p[..., BALLS, 1] - clearance[1]
    return np.minimum(ankle, ball) - floor


def foot_contacts(world_p: np.ndarray, clearance: np.ndarray, floor: float, fps: float,
                  height: float = SolveSettings.contact_height, speed: float = SolveSettings.contact_speed,
                  previous_balls: np.ndarray | None = None) -> np.ndarray:
    """(F, 2) bool: each foot planted on each frame, by a rule on foot height and velocity: its
    sole within height metres above the floor and its ball moving horizontally slower than speed
    m/s (finite difference with the previous frame; previous_balls (2, 3) the balls before the
    first frame, else the first frame counts as still). world_p (F, J, 3) metres."""
    balls = world_p[:, BALLS]
    before = balls[:1] if previous_balls is None else previous_balls[None]
    moved = np.diff(np.concatenate([before, balls]), axis=0)[..., [0, 2]]
    return (sole_heights(world_p, clearance, floor) < height) & (np.linalg.norm(moved, axis=-1) * fps < speed)


# -- frame-to-frame state ---------------------------------------------------------------------
def _hand_corrections(goals: np.ndarray, visible: np.ndarray, state: SolveState, step: float) -> tuple:
    """Per frame, each hand's wrist correction (F, 2, 3) and the weight (F, 2) of its target: the
    correction equals the goal (target - network wrist) once blended in; on entering and leaving
    the view it moves towards the goal (0 when hidden) by at most step metres a frame."""
    out, weights = np.zeros(goals.shape), np.zeros(goals.shape[:2])
    c, locked = state.correction.copy(), state.hand_locked.copy()
    for t in range(len(goals)):
        for k in (0, 1):
            goal = goals[t, k] if visible[t, k] else np.zeros(3)
            if visible[t, k] and (locked[k] or not state.started):
                c[k], locked[k] = goal, True
            else:
                locked[k] = False
                gap = goal - c[k]
                size = float(np.sqrt(gap @ gap))
                if size <= step:
                    c[k], locked[k] = goal, bool(visible[t, k])
                else:
                    c[k] = c[k] + gap * (step / size)
            out[t, k] = c[k]
            state.started = True if k else state.started
            if visible[t, k]:
                size = float(np.sqrt(goals[t, k] @ goals[t, k]))
                weights[t, k] = 1.0 if locked[k] else float(np.clip(1 - np.linalg.norm(goal - c[k]) / max(size, 1e-9), 0, 1))
    state.correction, state.hand_locked = c, locked
    return out, weights


def _foot_targets(balls: np.ndarray, contacts: np.ndarray, state: SolveState, release_frames: int) -> np.ndarray:
    """Per frame, where each ball should be (F, 2, 3): held where it first touched while planted;
    after a release the hold's offset from the network's ball shrinks to nothing over
    release_frames frames."""
    out = balls.copy()
    for t in range(len(balls)):
        for k in (0, 1):
            if contacts[t, k]:
                if not state.locked[k]:
                    state.locked[k] = True
                    state.lock[k] = balls[t, k] + state.release[k] * (state.release_left[k] / max(release_frames, 1))
                    state.release_left[k] = 0
                out[t, k] = state.lock[k]
            else:
                if state.locked[k]:
                    state.locked[k] = False
                    state.release[k], state.release_left[k] = state.lock[k] - balls[t, k], release_frames
                if state.release_left[k] > 0:
                    state.release_left[k] -= 1
                    out[t, k] = balls[t, k] + state.release[k] * (state.release_left[k] / max(release_frames, 1))
    return out


# -- the solve --------------------------------------------------------------------------------
def solve_frames(world_r: np.ndarray, world_p: np.ndarray, offsets: np.ndarray, hand_rotations: np.ndarray,
                 hand_positions: np.ndarray, visible: np.ndarray, floor: float, clearance: np.ndarray,
                 fps: float, state: SolveState | None = None,
                 settings: SolveSettings = SolveSettings()) -> tuple[np.ndarray, np.ndarray]:
    """Frames of a body pose with the arms and feet solved (module docstring).

    Args:
        world_r (F, J, 3, 3), world_p (F, J, 3): the network's body, world rotations and positions
            (metres) on the skeleton with these offsets (J, 3).
        hand_rotations (F, 2, 3, 3), hand_positions (F, 2, 3): the tracked wrists (left, right);
            any value where not visible (F, 2 bool).
        floor: the floor's height (metres); clearance (2,): :func:`foot_clearance`.
        fps: frames per second; state: carried between calls for a stream (None: a new stream).
    Returns:
        (world_r, world_p) solved, new arrays (float64).
    """
    state = SolveState() if state is None else state
    world_r, world_p = np.array(world_r, np.float64), np.array(world_p, np.float64)
    visible = np.asarray(visible, bool)
    frames = len(world_p)
    if settings.feet:
        # 1. the root lifted where a hip is too low for its foot to stand above the floor
        lowest_hip = floor + clearance[0] + 0.5 * np.linalg.norm(offsets[LEGS[0][2]])
        lift = np.maximum(lowest_hip - world_p[:, [LEGS[0][0], LEGS[1][0]], 1].min(-1), 0.0)
        world_p[:, :, 1] += lift[:, None]
        # 2. contacts, locks, floor
        contacts = foot_contacts(world_p, clearance, floor, fps, settings.contact_height, settings.contact_speed,
                                 state.previous_ball)
        state.previous_ball = world_p[-1, BALLS].copy()
        balls = _foot_targets(world_p[:, BALLS], contacts, state, int(round(settings.release_s * fps)))
        balls[..., 1] = np.maximum(balls[..., 1], floor + clearance[1])
        ball_offsets = np.stack([offsets[b] for b in BALLS])                             # (2, 3)
        ankles = balls - np.einsum("fkij,kj->fki", world_r[:, ANKLES], ball_offsets)
        raise_by = np.maximum(floor + clearance[0] - ankles[..., 1], 0.0)
        ankles[..., 1] += raise_by
        forward = world_r[:, PELVIS, :, 2]
        for k, leg in enumerate(LEGS):
            foot = world_r[:, BALLS[k]].copy()
            ankle_r = world_r[:, leg[2]].copy()
            middle, end = two_bone_ik(world_p[:, leg[0]], ankles[:, k], _pole(world_p, leg, forward),
                                      *_lengths(offsets, leg))
            _bend_chain(world_r, world_p, leg, middle, end)
            world_r[:, leg[2]], world_r[:, BALLS[k]] = ankle_r, foot      # the foot keeps its orientation
            world_p[:, BALLS[k]] = end + ankle_r @ offsets[BALLS[k]]
    if settings.arms:
        goals = np.nan_to_num(hand_positions - world_p[:, [ARMS[0][2], ARMS[1][2]]])
        corrections, weights = _hand_corrections(goals, visible, state, settings.blend_speed / fps)
        down = np.broadcast_to([0.0, -1.0, 0.0], (frames, 3))
        for k, arm in enumerate(ARMS):
            hand_r = world_r[:, arm[2]].copy()
            target = world_p[:, arm[2]] + corrections[:, k]
            middle, end = two_bone_ik(world_p[:, arm[0]], target, _pole(world_p, arm, down), *_lengths(offsets, arm))
            _bend_chain(world_r, world_p, arm, middle, end)
            if settings.hand_orientation:
                given = np.where(visible[:, k, None, None], np.nan_to_num(hand_rotations[:, k]), hand_r)
                world_r[:, arm[2]] = blend_rotations(world_r[:, arm[2]], given, weights[:, k])
    return world_r, world_p


def local_from_world(world_r: np.ndarray) -> np.ndarray:
    """(..., J, 3, 3) rotations relative to the parent (joint 0: world) from world rotations."""
    local = np.swapaxes(world_r[..., _PARENTS, :, :], -1, -2) @ world_r
    local[..., 0, :, :] = world_r[..., 0, :, :]
    return local


def world_rotations(local_quats: np.ndarray) -> np.ndarray:
    """(J, 3, 3) world rotations of one frame's local wxyz quaternions (J, 4) (joint 0 global)."""
    w, x, y, z = np.moveaxis(np.asarray(local_quats, np.float64), -1, 0)
    local = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
    world = np.empty_like(local)
    world[0] = local[0]
    for j in range(1, len(local)):
        world[j] = world[PARENTS[j]] @ local[j]
    return world


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(..., 4) unit wxyz quaternions, w >= 0, of rotation matrices (..., 3, 3) (Shepperd's method:
    from the largest of the four squared components)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    squares = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(squares, -1)
    s = np.sqrt(np.maximum(np.take_along_axis(squares, best[..., None], -1)[..., 0], 1e-12)) * 2   # 4 |q_best|
    a = m[..., 2, 1] - m[..., 1, 2]
    b = m[..., 0, 2] - m[..., 2, 0]
    c = m[..., 1, 0] - m[..., 0, 1]
    d = m[..., 0, 1] + m[..., 1, 0]
    e = m[..., 0, 2] + m[..., 2, 0]
    f = m[..., 1, 2] + m[..., 2, 1]
    candidates = np.stack([np.stack([s / 4, a / s, b / s, c / s], -1), np.stack([a / s, s / 4, d / s, e / s], -1),
                           np.stack([b / s, d / s, s / 4, f / s], -1), np.stack([c / s, e / s, f / s, s / 4], -1)], -2)
    q = np.take_along_axis(candidates, best[..., None, None], -2)[..., 0, :]
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def solve_body(motion: Motion, device_rotations, device_positions, visible, floor: float | None = None,
               eye=None, settings: SolveSettings = SolveSettings()) -> Motion:
    """A tracked body (any method's) with the arms solved to the tracked hands and the feet on the
    floor: :func:`solve_frames` over a whole motion, frame by frame state included.

    Args:
        motion: the body on the canonical skeleton (F frames at motion.fps).
        device_rotations (F, 3, 3, 3), device_positions (F, 3, 3): head (eyes), left and right
            wrist poses (humotion.sparse.signals.DEVICES order), metres; visible (F, 2) bool.
        floor: the floor height (metres); None: from the first second's head heights
            (:func:`floor_from_head`).
        eye: (3,) eye offset in the head frame (signals.eye_offset), needed when floor is None.
    Returns:
        the solved Motion (same skeleton, fps and name).
    """
    r = np.asarray(torch.as_tensor(device_rotations, dtype=torch.float64))
    p = np.asarray(torch.as_tensor(device_positions, dtype=torch.float64))
    if floor is None:
        from humotion.sparse.signals import eye_offset

        eye = eye_offset(motion.skeleton) if eye is None else eye
        floor = floor_from_head(p[:, 0, 1], motion.skeleton, np.asarray(eye), motion.fps, settings.floor_window_s)
    world_r, world_p = (x.double().numpy() for x in motion.world())
    offsets = np.asarray(motion.skeleton.offsets, np.float64)
    world_r, world_p = solve_frames(world_r, world_p, offsets, r[:, 1:], p[:, 1:], np.asarray(visible, bool), floor,
                                    foot_clearance(motion.skeleton), motion.fps, settings=settings)
    local = torch.from_numpy(local_from_world(world_r)).float()
    return Motion(motion.skeleton, rot.matrix_to_quat(local), torch.from_numpy(world_p[:, 0]).float(), motion.fps,
                  name=motion.name)
