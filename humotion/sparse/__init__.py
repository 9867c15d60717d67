"""Sparse tracking: full-body motion from a VR headset's head and (sometimes seen) hand poses.

Modules: signals (headset input signals synthesised from mocap, hand visibility in the headset
camera frustum), recording (recorded headset stream files: CSV / JSON, OpenXR / Unity axes).
"""
