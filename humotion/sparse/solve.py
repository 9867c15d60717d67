"""After the network: the arms solved so the wrists meet the tracked hands, the feet kept on the
floor and locked while planted. One compiled loop over frames (numba, :func:`solve_frames`)
runs both one live frame (SparseTracker.update: a batch of one, the state carried between calls)
and a whole recording (SparseTracker.track and :func:`solve_body`, which applies the same solve
to any method's output), so the two agree; its steps are pure functions of small arrays, also
callable from Python (:func:`two_bone_ik`, :func:`rotation_between`).

Dimension letters: T frames, J = 22 canonical joints. Units: metres, seconds; world frame Y up.

Per frame:

1. Floor: a height (world Y) given, or taken from the stream's first standing frames
   (:func:`running_floor`: the highest eye height in the first second, less the body's
   standing eye height).
2. Root lift: where a hip is below the floor or nearly (a person lying down, the body posed
   upright below the headset), the whole body is raised (``hip_height``).
3. Feet: a foot is in contact when its ball moves slowly and its sole is near the floor (the
   rule of :func:`foot_contacts`, which the metrics use, with looser thresholds: the network's
   planted feet slide) or, as a network's feet may float a few cm, near the lowest that sole has
   been lately or the other sole (``relative_contact``; causal: a running low that rises by
   ``contact_rise``); a looser height and speed keep it held. A contact holds the ball where it
   touched down, lowering it towards the floor as far as the straight leg reaches, and a release
   blends it back to the network's over ``release_s``. Ball and
   ankle are kept above the floor on every frame. Hip-knee-ankle two-bone IK places the
   ankle, the network's knee giving the swivel; the foot keeps the network's orientation.
4. Arms: a visible hand's wrist is reached by shoulder-elbow-wrist two-bone IK with the
   network's elbow as the pole (the swivel), and takes the hand's tracked orientation; a hand
   beyond the arm's reach turns the collar towards it first (up to ``collar_deg``). A hand
   entering the view is blended in, the wrist moving with the hand and closing the gap to it by at
   most ``blend_speed``; one leaving it is blended out, the wrist moving (relative to the head)
   by at most ``blend_speed`` towards the network's; so it does not jump even where the
   network's wrist does. A target out of reach stretches the arm towards it.

Bone lengths are the skeleton's: the canonical body scaled to the user's height, or calibrated
(SparseTracker.calibrate).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from humotion.kernels import compiled, rodrigues
from humotion.canonical import JOINTS, PARENTS
from humotion.motion import Motion
from humotion.skeleton import Skeleton

ARMS = tuple(tuple(JOINTS.index(f"{s}_{j}") for j in ("shoulder", "elbow", "wrist")) for s in ("left", "right"))
LEGS = tuple(tuple(JOINTS.index(f"{s}_{j}") for j in ("hip", "knee", "ankle")) for s in ("left", "right"))
BALLS = tuple(JOINTS.index(f"{s}_foot") for s in ("left", "right"))
ANKLES = tuple(leg[2] for leg in LEGS)
HEAD = JOINTS.index("head")
_PARENTS = np.array([max(p, 0) for p in PARENTS], np.int64)
_ARMS, _LEGS, _BALLS = np.array(ARMS, np.int64), np.array(LEGS, np.int64), np.array(BALLS, np.int64)
_COLLARS = np.array([PARENTS[a[0]] for a in ARMS], np.int64)
_CHANGED = np.array(sorted(set(np.concatenate([_COLLARS, _ARMS.ravel(), _LEGS.ravel(), _BALLS]))), np.int64)


CONTACT_HEIGHT, CONTACT_SPEED = 0.06, 0.3
"""The metrics' foot contact (:func:`foot_contacts`): a sole within 6 cm of the floor, its ball
moving horizontally slower than 0.3 m/s."""


@dataclass(frozen=True)
class SolveSettings:
    """What the solve does and its thresholds (metres, seconds)."""

    arms: bool = True
    """Solve the arms to the visible hands."""
    feet: bool = True
    """Lock planted feet and keep the feet above the floor."""
    hand_orientation: bool = True
    """Give the wrist the tracked hand's orientation."""
    blend_speed: float = 1.45
    """m/s: how fast a wrist moves at most while it blends from the network's wrist to a hand
    entering the view (relative to the hand, see blend_follows_hand), or back when the hand
    leaves it (relative to the head). 1.45 m/s: 4.8 cm a frame at the network's 30 fps, under
    the 5 cm a frame that counts as a jump (issue 27)."""
    blend_follows_hand: bool = True
    """While a wrist blends in, it moves with the hand (an offset from the hand shrinking by at
    most blend_speed), instead of chasing the hand from its own place relative to the head,
    which a hand moving faster than blend_speed left behind for the whole blend. False: the
    chase."""
    first_share: float = 0.5
    """Of blend_speed, the share a wrist may move on the frame its hand enters the view (with
    blend_follows_hand): that frame moves with the head, not with the hand (whose move from the
    frame before is unknown), so half the step is left for the hand's own move."""
    contact_height: float = 0.06
    """m: a sole at most this far above the floor can be in contact (with relative_contact, also
    a sole near its own recent lowest or the other foot's height, up to contact_ceiling)."""
    relative_contact: bool = True
    """Plant a slow foot also where its sole is within contact_margin of the lowest it has been
    lately (that low rising by contact_rise) or of the other sole, as long as it is under
    contact_ceiling: a network whose feet float a few cm above the floor still plants them.
    False: the fixed height alone (contact_height, hold_height)."""
    contact_margin: float = 0.03
    """m: how far above its recent lowest, or above the other sole, a sole may be to be planted
    (twice this to stay held)."""
    contact_rise: float = 0.1
    """m/s: how fast a foot's recent lowest sole rises while the foot is higher (it forgets)."""
    contact_ceiling: float = 0.10
    """m: no sole higher than this above the floor is planted, whatever its recent lowest."""
    settle_speed: float = 0.3
    """m/s: a held ball above the floor is lowered onto it at most this fast (with
    relative_contact: a planted foot stands on the floor)."""
    contact_speed: float = 0.6
    """m/s: a ball moving horizontally slower than this can be in contact (the network's feet
    slide while planted: twice the metrics' CONTACT_SPEED)."""
    release_s: float = 0.15
    """s: a released foot returns to the network's place over this time."""
    hold_height: float = 0.09
    """m: a planted foot stays planted while its sole is at most this far above the floor ..."""
    hold_speed: float = 1.5
    """m/s: ... and its ball (the network's) moves slower than this: looser than the rule that
    plants it, so a network's foot that slides while standing stays held."""
    lock_reach: float = 0.4
    """m: a planted foot is released when the network's ball moves this far from it (horizontally),
    or when the hip can no longer reach it."""
    collar_deg: float = 30.0
    """degrees: the most the collar turns towards a hand beyond the arm's reach (0: never)."""
    hip_height: float = 0.1
    """m: the lowest a hip may be above the floor (sitting or lying on it); a body posed lower
    (hanging below a headset near the floor) is raised to it."""
    floor_window_s: float = 1.0
    """s: the stream's first seconds in which the floor is taken (the user stands)."""


@dataclass
class SolveState:
    """What the solve carries from frame to frame of one stream (numpy arrays, changed in place).

    wrist_from_head (2, 3): where each wrist was put, from the head joint; hand_locked (2,): it
    follows its goal (the hand, or the network's wrist while unseen) exactly, blending done;
    was_seen (2,): the hands' visibility on the previous frame; blend_offset (2, 3): a wrist
    blending in, from its hand. previous_ball (2, 3): the network's balls on the
    previous frame; lowest_sole (2,): each sole's recent lowest height above the floor; locked (2,), lock (2, 3): where a planted ball is held; release (2, 3) the
    offset being blended out after a release, release_left (2,) its frames to go. counts (3,):
    frames solved, frames seen of the floor's window; highest_eye (1,): the highest eye height
    in that window (:func:`running_floor`)."""

    wrist_from_head: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    hand_locked: np.ndarray = field(default_factory=lambda: np.zeros(2, np.bool_))
    was_seen: np.ndarray = field(default_factory=lambda: np.zeros(2, np.bool_))
    blend_offset: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    previous_ball: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    lowest_sole: np.ndarray = field(default_factory=lambda: np.zeros(2))
    locked: np.ndarray = field(default_factory=lambda: np.zeros(2, np.bool_))
    lock: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    release: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    release_left: np.ndarray = field(default_factory=lambda: np.zeros(2, np.int64))
    counts: np.ndarray = field(default_factory=lambda: np.zeros(2, np.int64))
    highest_eye: np.ndarray = field(default_factory=lambda: np.full(1, -1e30))


def forget_places(state: SolveState) -> None:
    """Drop what the state ties to places of the world (planted feet, the wrists' blends), keeping
    the floor: for a stream whose network restarts at a new origin (a re-centred or teleported
    user), where the solve then goes on as a fresh one does."""
    state.locked[:] = False
    state.release_left[:] = 0
    state.was_seen[:] = False
    state.counts[0] = 0


# -- the body's own sizes ---------------------------------------------------------------------
def foot_clearance(skeleton: Skeleton) -> np.ndarray:
    """(2,) heights of the ankle and of the ball (foot joint) above the sole (the toe tips) when
    standing, metres, from the skeleton's rest pose."""
    rest = skeleton.rest_positions(torch.float64).numpy()
    toe = float(skeleton.rest_end_site_positions()[skeleton.end_site_names.index("left_toe")][1])
    return np.array([rest[ANKLES[0], 1] - toe, rest[BALLS[0], 1] - toe])


def arm_lengths(skeleton: Skeleton) -> np.ndarray:
    """(2,) left and right arm's reach from the shoulder (upper arm plus forearm), metres: the
    farthest the solve's two-bone IK puts a wrist from its shoulder."""
    offsets = skeleton.offsets.double().numpy()
    return np.array([np.linalg.norm(offsets[elbow]) + np.linalg.norm(offsets[wrist]) for _, elbow, wrist in ARMS])


def standing_eye_height(skeleton: Skeleton, eye) -> float:
    """Eye height above the sole of the skeleton standing in its rest pose, metres (eye: (3,) the
    eyes in the head joint's frame, humotion.sparse.signals.eye_offset)."""
    rest = skeleton.rest_positions(torch.float64).numpy()
    toe = float(skeleton.rest_end_site_positions()[skeleton.end_site_names.index("left_toe")][1])
    return float(rest[HEAD, 1] + np.asarray(eye, np.float64)[1] - toe)


@dataclass(frozen=True)
class BodyGeometry:
    """What the solve needs of a skeleton (the canonical body), computed once per stream: offsets
    (J, 3) metres, clearance (2,) (:func:`foot_clearance`), standing_eye (m,
    :func:`standing_eye_height`)."""

    offsets: np.ndarray
    clearance: np.ndarray
    standing_eye: float

    @classmethod
    def of(cls, skeleton: Skeleton, eye=None) -> "BodyGeometry":
        """eye: (3,) the eyes in the head frame (default: signals.eye_offset(skeleton))."""
        from humotion.sparse.signals import eye_offset

        eye = eye_offset(skeleton) if eye is None else eye
        return cls(np.ascontiguousarray(skeleton.offsets.double().numpy()), foot_clearance(skeleton),
                   standing_eye_height(skeleton, eye))


# -- feet and floor, as the metrics read them (numpy) ----------------------------------------
def sole_heights(world_p: np.ndarray, clearance: np.ndarray, floor) -> np.ndarray:
    """(..., T, 2) height above the floor of each foot's sole (left, right): the lower of ankle and
    ball, each less its standing clearance. world_p (..., T, J, 3) metres; clearance (2,)
    (:func:`foot_clearance`); floor: metres, one height or (..., T) per frame."""
    ankle = world_p[..., ANKLES, 1] - clearance[0]
    ball = world_p[..., BALLS, 1] - clearance[1]
    return np.minimum(ankle, ball) - np.asarray(floor)[..., None]


def foot_contacts(world_p: np.ndarray, clearance: np.ndarray, floor, fps: float,
                  height: float = CONTACT_HEIGHT, speed: float = CONTACT_SPEED) -> np.ndarray:
    """(T, 2) bool: each foot planted on each frame, by a rule on foot height and velocity: its
    sole (:func:`sole_heights`) less than height metres above the floor and its ball moving
    horizontally slower than speed m/s (its move from the frame before; the first frame counts
    as still). world_p (T, J, 3) metres. The metrics' rule (humotion.sparse.metrics.skating);
    the solve plants the network's feet by the same rule with its own thresholds
    (SolveSettings.contact_height, contact_speed), one frame at a time."""
    balls = world_p[:, BALLS][..., [0, 2]]
    moved = np.diff(np.concatenate([balls[:1], balls]), axis=0)
    return (sole_heights(world_p, clearance, floor) < height) & (np.sqrt(np.sum(moved * moved, -1)) * fps < speed)


def running_floor(head_heights: np.ndarray, standing_eye: float, fps: float,
                  window_s: float = SolveSettings.floor_window_s) -> np.ndarray:
    """(T,) the floor height known at each frame of a stream (metres, world Y), the rule of the
    solve: the highest eye height (head_heights (T,) metres) so far within the first window_s
    seconds, less the body's standing eye height; constant after the window (causal, so a live
    stream and its recording agree). Assumes the user stands up straight at some moment of it."""
    heights = np.asarray(head_heights, np.float64)
    inside = np.arange(len(heights)) < max(1, int(round(window_s * fps)))
    return np.maximum.accumulate(np.where(inside, heights, -np.inf)) - standing_eye


# -- geometry (compiled; vectors (3,), rotations (3, 3)) -----------------------------------
@compiled
def _mm(a, b):
    """a @ b for 3 x 3 matrices, written out (numba's @ calls BLAS: microseconds at this size)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return out


@compiled
def _mv(a, v):
    """a @ v for a 3 x 3 matrix and a vector, written out."""
    return np.array([a[0, 0] * v[0] + a[0, 1] * v[1] + a[0, 2] * v[2], a[1, 0] * v[0] + a[1, 1] * v[1] + a[1, 2] * v[2],
                     a[2, 0] * v[0] + a[2, 1] * v[1] + a[2, 2] * v[2]])


@compiled
def _norm(v):
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@compiled
def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@compiled
def _any_normal(u):
    """A unit vector normal to the unit vector u."""
    other = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = _cross(u, other)
    return n / _norm(n)


@compiled
def rotation_between(a, b):
    """(3, 3) the smallest rotation turning direction a (3,) onto direction b (3,) (Rodrigues'
    formula); opposite directions turn half a turn about an axis normal to a."""
    a = a / max(_norm(a), 1e-12)
    b = b / max(_norm(b), 1e-12)
    cos = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    if cos < -1 + 1e-9:         # half a turn about n normal to a: 2 n n^T - I
        n = _any_normal(a)
        return 2 * np.outer(n, n) - np.eye(3)     # (np.outer: no BLAS)
    v = _cross(a, b)            # I + [v]x + [v]x^2 / (1 + cos), with [v]x^2 = v v^T - |v|^2 I
    return _rodrigues(v, 1.0, 1.0 / (1.0 + cos))


@compiled
def _rodrigues(v, s, c):
    """humotion.kernels.rodrigues, as a new (3, 3) array."""
    out = np.empty((3, 3))
    rodrigues(v, s, c, out)
    return out


@compiled
def two_bone_ik(root, target, pole, upper, lower):
    """The middle and end joints of a two-bone chain reaching for a target.

    Args:
        root (3,): the chain's first joint (shoulder, hip), metres; it stays.
        target (3,): where the end joint (wrist, ankle) should be.
        pole (3,): a direction from the root, the side the middle joint (elbow, knee) bends to
            (only its part normal to the root-target line counts: it sets the swivel).
        upper, lower: bone lengths root-middle and middle-end, metres.
    Returns:
        (middle (3,), end (3,)), the bone lengths kept: end = target when it is within reach;
        else the chain points at the target, straight (too far) or folded (too near).
    """
    line = target - root
    distance = _norm(line)
    u = line / distance if distance > 1e-12 else np.array([0.0, -1.0, 0.0])
    reach = min(max(distance, abs(upper - lower) + 1e-6), upper + lower)
    along = (upper * upper - lower * lower + reach * reach) / (2 * reach)        # law of cosines
    height = math.sqrt(max(upper * upper - along * along, 0.0))
    side = pole - (pole[0] * u[0] + pole[1] * u[1] + pole[2] * u[2]) * u
    size = _norm(side)
    side = side / size if size > 1e-9 else _any_normal(u)
    return root + along * u + height * side, root + reach * u


@compiled
def _quat_to_matrix(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    m = np.empty((3, 3))
    m[0, 0], m[0, 1], m[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    m[1, 0], m[1, 1], m[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    m[2, 0], m[2, 1], m[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return m


@compiled
def _matrix_to_quat(m):
    """Unit wxyz quaternion, w >= 0, of a rotation matrix (Shepperd: from its largest component)."""
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if trace > m[0, 0] and trace > m[1, 1] and trace > m[2, 2]:
        s = 2 * math.sqrt(max(1 + trace, 1e-12))
        q[0], q[1], q[2], q[3] = s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2 * math.sqrt(max(1 + m[0, 0] - m[1, 1] - m[2, 2], 1e-12))
        q[0], q[1], q[2], q[3] = (m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] >= m[2, 2]:
        s = 2 * math.sqrt(max(1 - m[0, 0] + m[1, 1] - m[2, 2], 1e-12))
        q[0], q[1], q[2], q[3] = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2 * math.sqrt(max(1 - m[0, 0] - m[1, 1] + m[2, 2], 1e-12))
        q[0], q[1], q[2], q[3] = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4
    if q[0] < 0:
        q = -q
    return q / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])


@compiled
def blend_rotations(a, b, weight):
    """(3, 3) the rotation weight of the way from a (0) to b (1) along the shortest arc."""
    m = _mm(a.T, b)
    cos = min(max((m[0, 0] + m[1, 1] + m[2, 2] - 1) / 2, -1.0), 1.0)
    angle = math.acos(cos)
    axis = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    size = _norm(axis)
    if size < 1e-12:
        return b.copy() if weight >= 0.5 else a.copy()
    turn = angle * weight
    return _mm(a, _rodrigues(axis / size, math.sin(turn), 1 - math.cos(turn)))


@compiled
def _bend(world_r, world_p, a, b, c, middle, end):
    """Turn a chain's two bones (joints a, b, c of one frame's world_r (J, 3, 3), world_p (J, 3))
    onto new middle and end positions, in place: the smallest turn of each bone, the rest of
    each joint's frame carried along; the end joint turns with its parent."""
    turn_a = rotation_between(world_p[b] - world_p[a], middle - world_p[a])
    turn_b = _mm(rotation_between(_mv(turn_a, world_p[c] - world_p[b]), end - middle), turn_a)
    world_r[a] = _mm(turn_a, world_r[a])
    world_r[b] = _mm(turn_b, world_r[b])
    world_r[c] = _mm(turn_b, world_r[c])
    world_p[b] = middle
    world_p[c] = end


@compiled
def _reach_with_collar(world_r, world_p, collar, shoulder, elbow, wrist, target, most):
    """Turn the collar (and the arm with it) so the shoulder points towards target, by at most
    most radians, in place on one frame's world_r (J, 3, 3) and world_p (J, 3)."""
    bone, want = world_p[shoulder] - world_p[collar], target - world_p[collar]
    cos = (bone[0] * want[0] + bone[1] * want[1] + bone[2] * want[2]) / max(_norm(bone) * _norm(want), 1e-12)
    angle = math.acos(min(max(cos, -1.0), 1.0))
    if angle < 1e-9:
        return
    turn = rotation_between(bone, want)
    if angle > most:
        turn = blend_rotations(np.eye(3), turn, most / angle)
    origin = world_p[collar].copy()
    world_r[collar] = _mm(turn, world_r[collar])
    for j in (shoulder, elbow, wrist):
        world_r[j] = _mm(turn, world_r[j])
        world_p[j] = origin + _mv(turn, world_p[j] - origin)


@compiled
def _pole(world_p, a, b, c, fallback):
    """The network's bend of a chain (its middle joint's offset from the root-end line) plus 2 cm
    of a default direction, so that a straight limb has a side too."""
    line = world_p[c] - world_p[a]
    line = line / max(_norm(line), 1e-12)
    bend = world_p[b] - world_p[a]
    return bend - (bend[0] * line[0] + bend[1] * line[1] + bend[2] * line[2]) * line + 0.02 * fallback


# -- the solve (compiled) ---------------------------------------------------------------------
@compiled
def _solve(local, world_p, parents, offsets, clearance, standing_eye, hands_r, hands_p, visible, heads, floor_given,
           has_floor, fps, options, wrist_from_head, hand_locked, was_seen, blend_offset, previous_ball, lowest_sole,
           locked, lock, release, release_left, counts, highest_eye, arms, legs, balls, changed, out_local):
    """solve_frames' loop over frames (its docstring; options: feet, arms, hand orientation as
    0/1, blend_speed, contact_height, contact_speed, release_s, floor_window_s, lock_reach,
    hold_height, hold_speed, hip_height, collar_deg, blend_follows_hand as 0/1,
    first_share, relative_contact as 0/1, contact_margin, contact_rise, contact_ceiling,
    settle_speed).
    No NaN or infinity reaches here: fast math assumes there are none."""
    frames, joints = local.shape[0], local.shape[1]
    step = options[3] / fps
    head = HEAD
    release_frames = max(int(round(options[6] * fps)), 1)
    window = max(int(round(options[7] * fps)), 1)
    world_r = np.empty((joints, 3, 3))
    for t in range(frames):
        p = world_p[t]
        for j in range(joints):                                     # world rotations
            m = _quat_to_matrix(local[t, j])
            world_r[j] = m if j == 0 else _mm(world_r[parents[j]], m)
        floor = floor_given
        if not has_floor:                                           # 1. the floor
            if counts[1] < window:
                highest_eye[0] = max(highest_eye[0], heads[t])
                counts[1] += 1
            floor = highest_eye[0] - standing_eye
        if options[0] > 0:
            # 2. the body raised where a hip is too low for its foot to be above the floor
            lift = floor + options[11] - min(p[legs[0, 0], 1], p[legs[1, 0], 1])
            if lift > 0:
                p[:, 1] += lift
            forward = world_r[0][:, 2].copy()
            soles = np.empty(2)
            for k in range(2):
                soles[k] = min(p[legs[k, 2], 1] - clearance[0], p[balls[k], 1] - clearance[1]) - floor
                lowest_sole[k] = soles[k] if counts[0] == 0 else min(soles[k], lowest_sole[k] + options[17] / fps)
            for k in range(2):
                hip, knee, ankle, ball = legs[k, 0], legs[k, 1], legs[k, 2], balls[k]
                # 3. contact: a slow ball and a sole near the floor (the rule of foot_contacts), or
                # near its own recent lowest or the other sole; a planted ball held (lowered onto
                # the floor), released smoothly
                sole = soles[k]
                plant_height, hold_height = options[4], options[9]
                if options[15] > 0:
                    near = min(lowest_sole[k], soles[1 - k]) + options[16]
                    plant_height = max(plant_height, min(near, options[18]))
                    hold_height = max(hold_height, min(near + options[16], options[18]))
                dx, dz = p[ball, 0] - previous_ball[k, 0], p[ball, 2] - previous_ball[k, 2]
                moving = math.sqrt(dx * dx + dz * dz) * fps if counts[0] > 0 else 0.0
                previous_ball[k] = p[ball]
                target = p[ball].copy()
                if locked[k]:       # a hold the network's foot has left, or the hip cannot reach, ends
                    gx, gz = lock[k, 0] - p[ball, 0], lock[k, 2] - p[ball, 2]
                    leg = _norm(offsets[knee]) + _norm(offsets[ankle]) + _norm(offsets[ball])
                    if math.sqrt(gx * gx + gz * gz) > options[8] or _norm(lock[k] - p[hip]) > leg:
                        moving = options[10]
                planting = sole < plant_height and moving < options[5]
                if planting or (locked[k] and sole < hold_height and moving < options[10]):
                    if not locked[k]:
                        locked[k] = True
                        lock[k] = p[ball] + release[k] * (release_left[k] / release_frames)
                        release_left[k] = 0
                    if options[15] > 0:
                        lock[k, 1] = max(lock[k, 1] - options[19] / fps, floor + clearance[1])
                    target = lock[k].copy()
                else:
                    if locked[k]:
                        locked[k] = False
                        release[k] = lock[k] - p[ball]
                        release_left[k] = release_frames
                    if release_left[k] > 0:
                        release_left[k] -= 1
                        target = p[ball] + release[k] * (release_left[k] / release_frames)
                target[1] = max(target[1], floor + clearance[1])
                to_ball = _mv(world_r[ankle], offsets[ball])
                reach = target - to_ball
                if locked[k] and options[15] > 0:   # lowered only as far as the straight leg reaches
                    thigh_shin = 0.999 * (_norm(offsets[knee]) + _norm(offsets[ankle]))
                    across = math.sqrt((reach[0] - p[hip, 0]) ** 2 + (reach[2] - p[hip, 2]) ** 2)
                    if across < thigh_shin:
                        reach[1] = max(reach[1], p[hip, 1] - math.sqrt(thigh_shin ** 2 - across ** 2))
                reach[1] = max(reach[1], floor + clearance[0])
                # 4. hip-knee-ankle IK; the foot keeps the network's orientation
                ankle_r, foot_r = world_r[ankle].copy(), world_r[ball].copy()
                middle, end = two_bone_ik(p[hip], reach, _pole(p, hip, knee, ankle, forward),
                                          _norm(offsets[knee]), _norm(offsets[ankle]))
                _bend(world_r, p, hip, knee, ankle, middle, end)
                world_r[ankle], world_r[ball] = ankle_r, foot_r
                p[ball] = end + to_ball
        if options[1] > 0:
            down = np.array([0.0, -1.0, 0.0])
            for k in range(2):
                shoulder, elbow, wrist = arms[k, 0], arms[k, 1], arms[k, 2]
                # 5. where the wrist goes, relative to the head (which the headset places): the
                # hand while seen, else the network's wrist. After the hand enters the view, the
                # wrist follows the hand with an offset (where it was, from the hand) that shrinks
                # by at most step a frame, so it moves with the hand and never more than step
                # from the hand's own move (its first frame: at most first_share of step from
                # where it was, relative to the head); after the hand leaves, the wrist is moved towards the
                # network's wrist by at most step a frame (the network's wrist may jump then)
                seen = visible[t, k]
                own = p[wrist] - p[head]
                goal = hands_p[t, k] - p[head] if seen else own
                if counts[0] == 0:
                    wrist_from_head[k], hand_locked[k] = goal, True
                elif seen != was_seen[k]:
                    hand_locked[k] = False
                    blend_offset[k] = wrist_from_head[k] - goal
                if hand_locked[k]:
                    wrist_from_head[k] = goal
                elif seen and options[13] > 0:
                    size = _norm(blend_offset[k])
                    most = step * options[14] if seen != was_seen[k] else step
                    if size <= most:
                        wrist_from_head[k], hand_locked[k] = goal, True
                    else:
                        blend_offset[k] = blend_offset[k] * (1 - most / size)
                        wrist_from_head[k] = goal + blend_offset[k]
                else:
                    gap = goal - wrist_from_head[k]
                    size = _norm(gap)
                    if size <= step:
                        wrist_from_head[k], hand_locked[k] = goal, True
                    else:
                        wrist_from_head[k] = wrist_from_head[k] + gap * (step / size)
                was_seen[k] = seen
                weight = 1.0
                if seen and not hand_locked[k]:
                    weight = min(max(1 - _norm(goal - wrist_from_head[k]) / max(_norm(goal - own), 1e-9), 0.0), 1.0)
                # 6. a hand out of the arm's reach: the collar turned towards it (up to collar_deg)
                target = p[head] + wrist_from_head[k]
                upper, lower = _norm(offsets[elbow]), _norm(offsets[wrist])
                if options[12] > 0 and _norm(target - p[shoulder]) > upper + lower:
                    _reach_with_collar(world_r, p, parents[shoulder], shoulder, elbow, wrist, target,
                                       options[12] * math.pi / 180)
                # 7. shoulder-elbow-wrist IK, the network's elbow as the pole
                hand_r = world_r[wrist].copy()
                middle, end = two_bone_ik(p[shoulder], target,
                                          _pole(p, shoulder, elbow, wrist, down),
                                          _norm(offsets[elbow]), _norm(offsets[wrist]))
                _bend(world_r, p, shoulder, elbow, wrist, middle, end)
                if seen and options[2] > 0:
                    world_r[wrist] = blend_rotations(world_r[wrist], hands_r[t, k], weight)
                elif not seen:
                    world_r[wrist] = hand_r
        counts[0] += 1
        out_local[t] = local[t]
        for j in changed:                                            # local rotations of the joints moved
            out_local[t, j] = _matrix_to_quat(_mm(world_r[parents[j]].T, world_r[j]))


@functools.lru_cache(maxsize=8)
def _options(settings: SolveSettings) -> np.ndarray:
    """The settings as _solve reads them (read only)."""
    options = np.array([settings.feet, settings.arms, settings.hand_orientation, settings.blend_speed,
                        settings.contact_height, settings.contact_speed, settings.release_s, settings.floor_window_s,
                        settings.lock_reach, settings.hold_height, settings.hold_speed, settings.hip_height,
                        settings.collar_deg, settings.blend_follows_hand, settings.first_share,
                        settings.relative_contact, settings.contact_margin, settings.contact_rise,
                        settings.contact_ceiling, settings.settle_speed], np.float64)
    options.flags.writeable = False
    return options


def _finite(values) -> np.ndarray:
    """values as a contiguous float64 array, NaN (an unseen hand) as 0."""
    values = np.ascontiguousarray(values, np.float64)
    return values if np.isfinite(values).all() else np.nan_to_num(values)


def solve_frames(local: np.ndarray, world_p: np.ndarray, body: BodyGeometry, hand_rotations: np.ndarray,
                 hand_positions: np.ndarray, visible: np.ndarray, head_heights: np.ndarray, fps: float,
                 floor: float | None = None, state: SolveState | None = None,
                 settings: SolveSettings = SolveSettings()) -> tuple[np.ndarray, np.ndarray]:
    """Frames of a body pose with the arms and feet solved (module docstring).

    Args:
        local (T, J, 4): the network's local joint rotations, wxyz quaternions (joint 0 global);
        world_p (T, J, 3): its world joint positions, metres, on the skeleton of body
            (:class:`BodyGeometry`).
        hand_rotations (T, 2, 3, 3), hand_positions (T, 2, 3): the tracked wrists (left, right);
            anything where not visible ((T, 2) bool).
        head_heights (T,): the eyes' height, metres (for the floor when floor is None).
        fps: frames per second; floor: metres, None to take it from the first standing frames
            (:func:`running_floor`); state: carried between calls of a stream (None: a new one).
    Returns:
        (local (T, J, 4), world_p (T, J, 3)) solved, new float64 arrays.
    """
    state = SolveState() if state is None else state
    local = np.ascontiguousarray(local, np.float64)
    world_p = np.array(world_p, np.float64)
    out = np.empty_like(local)
    _solve(local, world_p, _PARENTS, body.offsets, body.clearance, body.standing_eye,
           _finite(hand_rotations), _finite(hand_positions), np.asarray(visible, np.bool_), np.asarray(head_heights, np.float64), 0.0 if floor is None else float(floor),
           floor is not None, float(fps), _options(settings), state.wrist_from_head, state.hand_locked, state.was_seen, state.blend_offset,
           state.previous_ball, state.lowest_sole, state.locked, state.lock, state.release, state.release_left, state.counts,
           state.highest_eye, _ARMS, _LEGS, _BALLS, _CHANGED, out)
    return out, world_p


def solve_body(motion: Motion, device_rotations, device_positions, visible, floor: float | None = None,
               eye=None, settings: SolveSettings = SolveSettings()) -> Motion:
    """A tracked body (any method's) with the arms solved to the tracked hands and the feet on the
    floor: :func:`solve_frames` over a whole motion, as SparseTracker applies it.

    Args:
        motion: the body on the canonical skeleton (T frames at motion.fps).
        device_rotations (T, 3, 3, 3), device_positions (T, 3, 3): head (eyes), left and right
            wrist poses (humotion.sparse.signals.DEVICES order), metres, tensors or arrays;
            visible (T, 2) bool.
        floor: the floor height (metres); None: from the first second's head heights
            (:func:`running_floor`).
        eye: (3,) eye offset in the head frame (default signals.eye_offset(motion.skeleton)).
    Returns:
        the solved Motion (same skeleton, fps and name).
    """
    r = np.asarray(torch.as_tensor(device_rotations, dtype=torch.float64))
    p = np.asarray(torch.as_tensor(device_positions, dtype=torch.float64))
    local, world_p = solve_frames(motion.rotations.double().numpy(), motion.world_positions().double().numpy(),
                                  BodyGeometry.of(motion.skeleton, eye), r[:, 1:], p[:, 1:],
                                  np.asarray(torch.as_tensor(visible)).astype(bool), p[:, 0, 1], motion.fps, floor,
                                  settings=settings)
    return Motion(motion.skeleton, torch.from_numpy(local).float(), torch.from_numpy(world_p[:, 0]).float(),
                  motion.fps, name=motion.name)
