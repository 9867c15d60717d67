"""Seeing motions in a browser: :class:`MotionViewer` (non-blocking) and :func:`serve` (blocking).

Needs no network: viser serves its prebuilt web client from its own wheel.
"""

from humotion.viewer.app import PALETTE, MotionViewer, bone_segments, serve

__all__ = ["MotionViewer", "serve", "bone_segments", "PALETTE"]
