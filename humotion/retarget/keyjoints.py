"""Key joints of any humanoid rig, found from joint names and, where names say nothing, the tree.

Key points carry the canonical body's names (humotion.canonical): the 22 JOINTS (pelvis,
spine1-3 with spine3 the chest where arms and neck branch, neck, head, and per side collar,
shoulder = upper arm, elbow, wrist, hip = upper leg, knee, ankle, foot = toes) and the 5
END_SITES (head_top, {side}_hand, {side}_toe) that give the last bones a direction.

How they are found:
1. The five extremities, each wrist, each ankle and the head, by name: the shallowest joint
   whose name says hand/wrist, foot/ankle or head (not a finger, toe or helper bone), its side
   from a left/right marker (LeftArm, CC_Base_L_Hand, thigh_l, lfemur beside rfemur).
   Extremities the names miss come from the tree's shape: the five leaves farthest apart; the
   three that share the deepest branch point are the arms and the head (the head's is the
   shortest chain), the other two the legs; left is +X in the rest pose.
2. The rest follows the tree: knee and hip are the ankle's nearest ancestors, elbow, shoulder
   and collar the wrist's (helper bones such as twists skipped); the chest is where the two
   shoulders meet, the pelvis where legs and chest meet; spine1-3 lie on the path between
   them, the neck on the path from the chest to the head.
Every step takes a user's override (joint name for a key point) first, so fixing one joint fixes
the ones found from it. A rig with a head and two hands but nothing leg-like hanging below its
chest (an upper-body avatar) has no legs: its leg key points all sit on the pelvis (has_legs).
humotion.canonical maps every rig onto the canonical body with these key joints.
"""

from __future__ import annotations

import re

import torch

from humotion.canonical import END_SITES, JOINTS
from humotion.skeleton import Skeleton

SIDES = ("left", "right")
LEG_JOINTS = ("hip", "knee", "ankle", "foot")
KEY_POINTS: tuple[str, ...] = JOINTS + END_SITES

# Helper bones never serve as key joints when walking up a limb.
_HELPER = re.compile(r"twist|share|roll|helper|nub|end|dummy|adjust|corrective|ctrl|pole", re.I)
_FINGER = re.compile(r"thumb|index|mid|ring|pinky|little|finger|carpal", re.I)
_TOE = re.compile(r"toe|ball|heel|step", re.I)
# A middle limb joint named as one: an elbow or knee its rig calls so is trusted whatever the
# lengths (a stylised character's forearm may be twice its upper arm).
_NAMED_MIDDLE = re.compile(r"elbow|knee|fore.?arm|lower.?arm|low.?arm|shin|calf|lower.?leg|low.?leg", re.I)
_ROLES = {
    "wrist": (re.compile(r"hand|wrist", re.I), _FINGER),
    "ankle": (re.compile(r"foot|ankle", re.I), _TOE),
    "head": (re.compile(r"head", re.I), re.compile(r"top|end|nub", re.I)),
}


class Tree:
    """Rest geometry and ancestry of a skeleton, for the searches below: rest (J, 3) float64
    tensor, metres; per joint, as lists: bone (its offset's length, 0 for the root) and from_root
    (the bones' length down to it), metres, depth (its ancestors) and side (+1 left, -1 right,
    0 none, from its name)."""

    def __init__(self, skeleton: Skeleton):
        self.skeleton = skeleton
        self.names = skeleton.names
        self.parents = skeleton.parents
        self.rest = skeleton.rest_positions(torch.float64)
        # Lists: the searches below are many small scalar steps.
        self.bone = [0.0] + skeleton.offsets.double().norm(dim=1).tolist()[1:]
        self.depth = skeleton.depth().tolist()
        self.from_root = []
        for j, p in enumerate(self.parents):
            self.from_root.append(self.bone[j] + (self.from_root[p] if p >= 0 else 0.0))
        self.children = [skeleton.children(j) for j in range(skeleton.num_joints)]
        self.side = [self._name_side(n) for n in self.names]

    def ancestors(self, j: int) -> list[int]:
        """j and its ancestors, j first."""
        out = [j]
        while self.parents[out[-1]] >= 0:
            out.append(self.parents[out[-1]])
        return out

    def lca(self, *joints: int) -> int:
        common = set(self.ancestors(joints[0]))
        for j in joints[1:]:
            common &= set(self.ancestors(j))
        return max(common, key=lambda a: self.depth[a])

    def path(self, top: int, bottom: int) -> list[int]:
        """Joints strictly below top down to bottom (inclusive); bottom must descend from top."""
        chain = self.ancestors(bottom)
        return chain[: chain.index(top)][::-1]

    def upper(self, j: int) -> int | None:
        """Nearest ancestor of j that is not a helper bone (twist, share, roll, ...)."""
        p = self.parents[j]
        while p >= 0 and _HELPER.search(self.names[p]):
            p = self.parents[p]
        return p if p >= 0 else None

    def subtree(self, j: int) -> list[int]:
        out, todo = [], [j]
        while todo:
            k = todo.pop()
            out.append(k)
            todo.extend(self.children[k])
        return out

    def _name_side(self, name: str) -> int:
        """+1 left, -1 right, 0 when the name has no side marker."""
        lower = name.lower()
        if "left" in lower:
            return 1
        if "right" in lower:
            return -1
        tokens = re.split(r"[^A-Za-z0-9]+", name)
        if "L" in tokens or "l" in tokens:
            return 1
        if "R" in tokens or "r" in tokens:
            return -1
        # A one-letter prefix counts when the other side's joint exists (lfemur / rfemur).
        swap = {"l": "r", "r": "l", "L": "R", "R": "L"}
        if name[:1] in swap and swap[name[0]] + name[1:] in self.skeleton.names:
            return 1 if name[0] in "lL" else -1
        return 0


def _by_name(tree: Tree, role: str, side: int) -> int | None:
    """Shallowest joint on a side whose name says role and is no finger, toe or helper."""
    wanted, unwanted = _ROLES[role]
    found = [j for j, n in enumerate(tree.names)
             if tree.side[j] == side and wanted.search(n) and not unwanted.search(n) and not _HELPER.search(n)]
    return min(found, key=lambda j: tree.depth[j]) if found else None


def _leaves(tree: Tree) -> list[tuple[int, float]]:
    """(joint, extra length) of every leaf: an end site or a leaf joint without one, both
    counted as the end of their parent's bone."""
    sk = tree.skeleton
    out = list(zip(sk.end_site_parents, sk.end_site_offsets.double().norm(dim=1).tolist()))
    with_end = set(sk.end_site_parents)
    return out + [(tree.parents[j], tree.bone[j]) for j in range(1, sk.num_joints)
                  if not tree.children[j] and j not in with_end]


def _end_of_long_bones(tree: Tree, chain: list[int]) -> int | None:
    """The joint ending the two longest consecutive bones of a chain (thigh and shin: the ankle;
    upper arm and forearm: the wrist)."""
    if len(chain) < 3:
        return None
    i = max(range(1, len(chain) - 1), key=lambda i: tree.bone[chain[i]] + tree.bone[chain[i + 1]])
    return chain[i + 1]


def extremities_by_topology(tree: Tree) -> dict[str, int]:
    """Wrists, ankles and head from the tree's shape alone (empty dict when it is no humanoid)."""
    leaves = _leaves(tree)
    if len(leaves) < 5:
        return {}

    def distance(a, b):
        (ja, ea), (jb, eb) = a, b
        return tree.from_root[ja] + ea + tree.from_root[jb] + eb - 2 * tree.from_root[tree.lca(ja, jb)]

    # Farthest-point sampling: a fingertip, the other hand, the feet, the head.
    picked = [max(leaves, key=lambda leaf: tree.from_root[leaf[0]] + leaf[1])]
    while len(picked) < 5:
        picked.append(max(leaves, key=lambda leaf: min(distance(leaf, q) for q in picked)))
    joints = [j for j, _ in picked]
    pelvis = tree.lca(*joints)
    branch = [tree.path(pelvis, j)[0] if j != pelvis else j for j in joints]
    upper = [j for j, b in zip(joints, branch) if branch.count(b) == 3]
    legs = [j for j, b in zip(joints, branch) if branch.count(b) != 3]
    if len(upper) != 3 or len(legs) != 2:
        return {}
    chest = tree.lca(*upper)
    head_leaf = min(upper, key=lambda j: tree.from_root[j])
    arms = [j for j in upper if j != head_leaf]
    # The head is where the face's bones (eyes, jaw) fork, else the joint of the head's end.
    forks = [j for j in tree.path(chest, head_leaf) if len(tree.children[j]) >= 2]
    found = {"head": forks[0] if forks else head_leaf}
    for kind, pair, top in (("wrist", arms, chest), ("ankle", legs, pelvis)):
        left_first = sorted(pair, key=lambda j: -float(tree.rest[tree.path(top, j), 0].mean()))  # left is +X
        ends = []
        for leaf in left_first:
            chain = [top] + tree.path(top, leaf)
            # A hand is where the fingers branch; else (and for feet) the end of the two long bones.
            forks = [j for j in chain[2:] if len(tree.children[j]) >= 2] if kind == "wrist" else []
            ends.append(forks[-1] if forks else _end_of_long_bones(tree, chain))
        if len(set(ends)) == 2:  # one joint for both sides: two tips of the one limb there is, no pair
            found.update({f"{side}_{kind}": end for side, end in zip(SIDES, ends) if end is not None})
    return found


class MissingKeyJoints(ValueError):
    """A rig lacks key joints: names them and says how to name them in an override file."""

    def __init__(self, label: str, missing: dict[str, str]):
        self.missing = missing
        listed = "; ".join(f"{k} ({why})" for k, why in missing.items())
        example = ", ".join(f'"{k}": "<joint name>"' for k in list(missing)[:2])
        super().__init__(
            f"{label or 'rig'}: cannot find key joint(s) {listed}. Name them in an override file "
            f"(JSON or TOML) given with --overrides: {{\"joints\": {{{example}}}}}")


def find_key_joints(skeleton: Skeleton, overrides: dict[str, str] | None = None, label: str = "") -> dict[str, str | None]:
    """Key point -> joint (or end-site) name for every name in KEY_POINTS.

    overrides: key point -> joint name, taken before anything is searched.
    Joints a rig lacks (fewer spine joints, no collar or neck) take their canonical child's joint,
    so the bone between them has no length; end points it lacks are None. Raises
    MissingKeyJoints naming what cannot be found (a limb joint, the head, the chest).
    """
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(KEY_POINTS))
    if unknown:
        raise ValueError(f"{label or 'rig'}: unknown key joint(s) {', '.join(unknown)} in overrides; "
                         f"key joints are {', '.join(KEY_POINTS)}")
    points = set(skeleton.names) | set(skeleton.end_site_names)
    absent = sorted(v for v in overrides.values() if v not in points)
    if absent:
        raise ValueError(f"{label or 'rig'}: override names joint(s) {', '.join(absent)} the skeleton does not have")
    tree = Tree(skeleton)
    index = {n: i for i, n in enumerate(skeleton.names)}
    found: dict[str, int | None] = {k: index.get(v) for k, v in overrides.items() if k in JOINTS}
    missing: dict[str, str] = {}

    # 1. Extremities: overrides, then names, then the tree's shape.
    topology = None
    for key, role, side in [("head", "head", 0)] + [(f"{s}_{r}", r, sgn) for r in ("wrist", "ankle")
                                                      for s, sgn in zip(SIDES, (1, -1))]:
        if found.get(key) is None:
            found[key] = _by_name(tree, role, side)
        if found[key] is None:
            topology = extremities_by_topology(tree) if topology is None else topology
            found[key] = topology.get(key)
        if found[key] is None:
            missing[key] = f"no joint named like a {role}, and the tree's shape does not show one"
    legs = not (set(missing) <= {"left_ankle", "right_ankle"} and missing and _legless(tree, found))
    if not legs:  # an upper-body rig: its leg key points all sit on the pelvis (see has_legs)
        missing.clear()
    if missing:
        raise MissingKeyJoints(label, missing)

    # 2. Limbs, walking up from the extremities.
    limbs = (("ankle", "knee", "hip", "leg"), ("wrist", "elbow", "shoulder", "arm"))
    for side in SIDES:
        for end, mid, top, words in limbs[0 if legs else 1:]:
            for lower, upper in ((end, mid), (mid, top)):
                key = f"{side}_{upper}"
                if found.get(key) is None:
                    below = found[f"{side}_{lower}"]
                    found[key] = tree.upper(below) if below is not None else None
            _check_limb(tree, found, side, end, mid, top, words, missing)
    if missing:
        raise MissingKeyJoints(label, missing)
    for side in SIDES:
        collar = f"{side}_collar"
        if found.get(collar) is None:
            above = tree.upper(found[f"{side}_shoulder"])
            other = found[f"{'right' if side == 'left' else 'left'}_shoulder"]
            # A collar belongs to one arm: it is no ancestor of the other shoulder.
            found[collar] = above if above is not None and above not in tree.ancestors(other) else None

    # 3. Trunk: chest where the arms meet, pelvis where legs and chest meet, paths between.
    if found.get("spine3") is None:
        found["spine3"] = tree.lca(found["left_shoulder"], found["right_shoulder"])
    if found.get("pelvis") is None and legs:
        found["pelvis"] = tree.lca(found["left_hip"], found["right_hip"], found["spine3"])
    elif found.get("pelvis") is None:  # no legs: a joint named hip or pelvis above the chest, else the root
        trunk = tree.ancestors(found["spine3"])
        found["pelvis"] = next((j for j in trunk if re.search(r"hip|pelvis", tree.names[j], re.I)), trunk[-1])
    spine = tree.path(found["pelvis"], found["spine3"]) if found["spine3"] != found["pelvis"] else []
    if not spine:
        raise MissingKeyJoints(label, {"spine3": "the arms branch off the pelvis itself: no chest joint"})
    if found.get("spine1") is None:
        found["spine1"] = spine[0]
    if found.get("spine2") is None:  # with fewer than three spine joints, spine2 is the chest
        found["spine2"] = spine[len(spine) // 2] if len(spine) >= 3 else found["spine3"]
    if found.get("neck") is None:
        neck = tree.path(found["spine3"], found["head"]) if found["head"] in tree.subtree(found["spine3"]) else []
        found["neck"] = neck[0] if neck else found["head"]
    for side in SIDES:
        if not legs:
            found.update({f"{side}_{k}": found["pelvis"] for k in LEG_JOINTS})
        toes = f"{side}_foot"
        if found.get(toes) is None:
            found[toes] = _toes(tree, found[f"{side}_ankle"])

    names: dict[str, str | None] = {k: None if found.get(k) is None else skeleton.names[found[k]] for k in JOINTS}
    for side in SIDES:
        collar = f"{side}_collar"
        names[collar] = names[collar] or names[f"{side}_shoulder"]
        ankle = found[f"{side}_ankle"]
        if names[f"{side}_foot"] is None and legs:  # no toe joint: the ankle's end site points along the foot
            ends = [e for e, p in zip(skeleton.end_site_names, skeleton.end_site_parents) if p == ankle]
            if not ends:
                missing[f"{side}_foot"] = f"no toe joint or end site below {skeleton.names[ankle]}"
            names[f"{side}_foot"] = ends[0] if ends else None
    if missing:
        raise MissingKeyJoints(label, missing)
    names.update(_end_points(tree, found, legs))
    names.update(overrides)  # end sites given for joints (toes as the ankle's end) included
    return names


def _check_limb(tree: Tree, found: dict, side: str, end: str, mid: str, top: str, words: str, missing: dict) -> None:
    """Thigh and shin (upper arm and forearm) must both be real bones of like length: a rig
    without a knee makes the hip-socket bone the 'thigh' and a shin as long as the leg. A middle
    joint named as an elbow or knee is trusted (_NAMED_MIDDLE)."""
    a, b, c = (found.get(f"{side}_{k}") for k in (top, mid, end))
    if b is None:
        missing[f"{side}_{mid}"] = f"nothing above the {end}"
        return
    if a is None:
        missing[f"{side}_{top}"] = f"nothing above the {mid}"
        return
    upper = float((tree.rest[b] - tree.rest[a]).norm())
    lower = float((tree.rest[c] - tree.rest[b]).norm())
    names = tree.names
    if _NAMED_MIDDLE.search(names[b]) and not _HELPER.search(names[b]):
        return
    if lower > 1.8 * upper:
        missing[f"{side}_{mid}"] = (f"the {words} from {names[a]} over {names[b]} to {names[c]} has no joint "
                                    f"half way ({upper:.2f} m then {lower:.2f} m)")
    elif upper > 3.0 * lower:
        missing[f"{side}_{end}"] = (f"the {words} from {names[a]} over {names[b]} to {names[c]} ends too early "
                                    f"({upper:.2f} m then {lower:.2f} m)")


def _legless(tree: Tree, found: dict) -> bool:
    """Whether a rig with a head and two hands has no legs: nothing hangs off its trunk below
    the chest (where the hands' chains meet) as long as 40% of an arm."""
    chest = tree.lca(found["left_wrist"], found["right_wrist"])
    trunk, upper = set(tree.ancestors(chest)), set(tree.subtree(chest))
    hanging = [j for j in range(len(tree.names)) if j not in trunk and j not in upper]
    reach = max((tree.from_root[j] - tree.from_root[tree.lca(j, chest)] for j in hanging), default=0.0)
    arm = tree.from_root[found["left_wrist"]] - tree.from_root[chest]
    return found.get("head") is not None and reach < 0.4 * arm


def has_legs(key_joints: dict[str, str | None]) -> bool:
    """False for an upper-body rig, whose leg key points find_key_joints puts on the pelvis."""
    return key_joints["left_ankle"] != key_joints["pelvis"]


def _toes(tree: Tree, ankle: int) -> int | None:
    """The toe joint below an ankle: a child named toe/ball, else the non-helper child with the
    most joints below it."""
    children = [c for c in tree.children[ankle] if not _HELPER.search(tree.names[c])]
    named = [c for c in children if re.search(r"toe|ball", tree.names[c], re.I)]
    return (named or sorted(children, key=lambda c: -len(tree.subtree(c))) or [None])[0]


def _end_points(tree: Tree, found: dict, legs: bool = True) -> dict[str, str | None]:
    """head_top, hands and toe tips: an end site of the joint, else a middle-finger / middle-toe
    joint (not at the joint itself, as CMU BVH's zero-length LeftFingerBase is; of several, one
    named middle, else the one most along the forearm), else None (the template's bone is used).
    A hand named by no joint or end site is the nearest joint below the wrist most along the forearm."""
    sk = tree.skeleton

    def end_site(j):  # an end site of j, else its only child when that is a leaf (ends stored as joints)
        site = next((e for e, p in zip(sk.end_site_names, sk.end_site_parents) if p == j), None)
        only = tree.children[j][0] if len(tree.children[j]) == 1 else None
        return site or (tree.names[only] if only is not None and not tree.children[only] else None)

    def middle(j, pattern, axis=torch.zeros(3, dtype=torch.float64)):
        away = {k: tree.rest[k] - tree.rest[j] for k in tree.subtree(j)[1:]}
        below = [k for k, v in away.items() if re.search(pattern, tree.names[k], re.I) and v.norm() > 1e-4]
        return tree.names[min(below, key=lambda k: (not re.search("mid", tree.names[k], re.I), tree.depth[k],
                                                   -float(away[k] @ axis / away[k].norm())))] if below else None

    out = {"head_top": end_site(found["head"])}
    for side in SIDES:
        wrist, toes = found[f"{side}_wrist"], found.get(f"{side}_foot")
        forearm = tree.rest[wrist] - tree.rest[found[f"{side}_elbow"]]
        out[f"{side}_hand"] = middle(wrist, r"mid|finger", forearm) or end_site(wrist) or middle(wrist, "", forearm)
        if toes is None or not legs:  # toes given as the ankle's end site, or no legs
            out[f"{side}_toe"] = None
        else:
            out[f"{side}_toe"] = end_site(toes) or middle(toes, r"mid")
    return out
