"""Retargeting motion between skeletons of different structure and proportions.

Classical half: understand any BVH/ASF rig (key joints, six body parts, membership matrix,
rest-pose alignment) and transfer motion onto it with foot contacts kept.

    from humotion.retarget import Rig, retarget
    result = retarget(motion, target_skeleton)            # or Rig.of(skeleton, overrides)
"""

from humotion.retarget.classical import check_finite, copy_rotations, retarget
from humotion.retarget.contacts import contacts_kept, foot_contacts, foot_skating
from humotion.retarget.keyjoints import KEY_POINTS, MissingKeyJoints, find_key_joints
from humotion.retarget.parts import PARTS, label_parts, load_overrides, membership_matrix
from humotion.retarget.rig import Rig, correspondence, rest_difference

__all__ = [
    "Rig", "retarget", "copy_rotations", "check_finite", "correspondence", "rest_difference",
    "find_key_joints", "KEY_POINTS", "MissingKeyJoints", "PARTS", "label_parts", "membership_matrix",
    "load_overrides", "foot_contacts", "foot_skating", "contacts_kept",
]
