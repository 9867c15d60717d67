"""Retargeting motion between skeletons of different structure and proportions.

Classical: understand any BVH/ASF rig (key joints, six body parts, membership matrix, rest-pose
alignment) and transfer motion onto it with foot contacts kept. Learned (experimental): the
spec's body-part attention networks, trained unpaired between the 31-joint CMU skeleton and the
100-joint game rig (humotion.retarget.learned; less accurate than the classical retargeter).

    from humotion.retarget import Rig, retarget
    result = retarget(motion, target_skeleton)            # or Rig.of(skeleton, overrides)
"""

from humotion.retarget.classical import check_finite, copy_rotations, retarget
from humotion.retarget.contacts import contacts_kept, foot_contacts, foot_skating
from humotion.retarget.keyjoints import KEY_POINTS, MissingKeyJoints, find_key_joints
from humotion.retarget.learned import retarget_learned
from humotion.retarget.parts import PARTS, label_parts, load_overrides, membership_matrix
from humotion.retarget.rig import Rig, correspondence, rest_difference

__all__ = [
    "Rig", "retarget", "retarget_learned", "copy_rotations", "check_finite", "correspondence", "rest_difference",
    "find_key_joints", "KEY_POINTS", "MissingKeyJoints", "PARTS", "label_parts", "membership_matrix",
    "load_overrides", "foot_contacts", "foot_skating", "contacts_kept",
]
