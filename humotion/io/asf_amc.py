"""Acclaim ASF/AMC: the skeleton (.asf) and motion (.amc) files of the CMU and HDM05 databases.

Why a parser of our own: no maintained PyPI package reads ASF/AMC with what humotion needs:
every bone's dof list (any subset and order of rx ry rz tx ty tz l), its axis rotation in any
axis order, joint limits, the root's channel order, units, gzip, and errors that name the file
and line. The format is small (Acclaim's 1994 spec, as written by VICON BodyBuilder), so it is
parsed here directly: humotion.io.asf reads the skeleton, humotion.io.amc the motion (and
finds the ASF that goes with an AMC file); this module is their public face.

How the file maps onto humotion's Skeleton (metres, Y up, +Z forward; the CMU/HDM05 ASF axes
already are Y up, +Z forward, a character's left = +X, so no axis change is needed):

- joints are the root plus one joint per bone, named by the bone, each located at its bone's
  START; a joint's rotation turns its own bone. So joint "lfemur" is the hip and "ltibia" the
  knee. The offset of a joint is its parent bone's direction * length (the root's children sit
  on the root). A bone with no children gets an end site "<bone>_end" at its end.
- lengths: ``:units length L`` means one file unit is 1/L inch (CMU FAQ: metres =
  value * (1/0.45) * 0.0254 for L = 0.45), for bone lengths and root translations alike.
- every bone's rest orientation is the world's (ASF directions are world vectors), so the local
  rotation of a joint is ``C @ M @ C^-1``, C the bone's ``axis`` rotation and M the AMC motion
  rotation built from the frame's dof values. Both are Euler angles composed in the written
  order, each later rotation about the fixed (world/parent) axes: "rx ry rz" gives
  M = Rz @ Ry @ Rx (roma's extrinsic convention "xyz"), and "axis ax ay az XYZ" likewise gives
  C = Rz(az) @ Ry(ay) @ Rx(ax). This is what the CMU/USC mocap player does, and
  tests/test_amc_vs_bvh.py proves it against CMU's BVH conversion of the same take, read by
  humotion.io.bvh: hips, legs and lower spine agree to 0.01 mm on all 2751 frames of 01_01,
  where the intrinsic reading ("XYZ", M = Rx @ Ry @ Rz) puts an ankle up to 1.65 m off.
- the root: position from its TX TY TZ channels plus the ASF root ``position``; rotation from its
  RX RY RZ channels in the ``order`` given, conjugated by the ``orientation``/``axis`` rotation
  in the same way as a bone.
- bone translation dofs (tx ty tz, rare) move the joint by C @ t in its parent's frame, and "l"
  stretches the bone along its direction (its child joints move; end sites keep the rest length);
  both become Motion.joint_offsets.
"""

from humotion.io.amc import find_asf, read_amc
from humotion.io.asf import INCH, AsfSkeleton, read_asf

__all__ = ["AsfSkeleton", "read_asf", "read_amc", "find_asf", "INCH"]
