"""humotion: partial observations of people -> full-body 3D motion, bodies and retargeting."""

from humotion.motion import Motion
from humotion.skeleton import Skeleton, forward_kinematics

__all__ = ["Motion", "Skeleton", "forward_kinematics"]
__version__ = "0.1.0"
