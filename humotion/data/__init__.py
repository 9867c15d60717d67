"""Mocap data: collections of motion files, subject splits, training windows, augmentation."""

from humotion.data.augment import RandomAugment, change_speed, mirror, rotate_yaw, yaw_quaternion
from humotion.data.cache import CACHE_VERSION, default_cache_dir
from humotion.data.root import default_data_dir
from humotion.data.collection import Clip, MotionCollection, Skipped, skeleton_signature, subject_id
from humotion.data.split import split_subjects
from humotion.data.windows import MotionWindows

__all__ = [
    "MotionCollection", "Clip", "Skipped", "MotionWindows", "CACHE_VERSION", "default_cache_dir", "default_data_dir",
    "skeleton_signature", "split_subjects", "subject_id",
    "RandomAugment", "change_speed", "mirror", "rotate_yaw", "yaw_quaternion",
]
