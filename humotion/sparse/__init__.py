"""Sparse tracking: whole-body motion, online, from a headset's head pose and the hands when seen.

See specs/sparse-tracking.md. Modules: signals (what a headset observes), recording (headset
frames and streams, stream files), model (SparsePoser, SparseOutput), losses, batches and train
(training), refine (fit after the network), tracker (SparseTracker, online and whole
recordings), metrics (evaluation).
"""

from humotion.sparse.recording import HeadsetFrame, HeadsetStream, read_recording, write_recording
from humotion.sparse.tracker import SparseTracker, TrackedPose

__all__ = ["HeadsetFrame", "HeadsetStream", "SparseTracker", "TrackedPose", "read_recording", "write_recording"]
