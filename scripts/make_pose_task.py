"""Build humotion/assets/capture/pose_landmarker_full.task from the BlazePose models in mediapipe 0.10.21.

mediapipe 0.10.21's wheel bundles BlazePose (Apache-2.0, Google) as two bare TFLite files for its
legacy `solutions.pose` API. Newer mediapipe (the runtime humotion uses, numpy 2) ships no models;
its Tasks `PoseLandmarker` reads a `.task` bundle instead: an uncompressed, 4-byte aligned zip
holding `pose_detector.tflite` and `pose_landmarks_detector.tflite`, each carrying TFLite metadata
that tells the Tasks image preprocessor how to normalise the input image. This script copies the
two models out of the installed 0.10.21 package, writes that metadata and packs the bundle.

0.10.21 needs numpy < 2 and 1.2.2's metadata writer lacks its compiled helper, so run this in a
throwaway virtual environment (it installs no torch):

    python3.11 -m venv /tmp/mp010
    /tmp/mp010/bin/pip install mediapipe==0.10.21 "numpy<2"
    /tmp/mp010/bin/python scripts/make_pose_task.py

Input normalisation, as in 0.10.21's own graphs (pose_detection_cpu.pbtxt and
pose_landmark_by_roi_cpu.pbtxt): the detector (224 x 224 RGB) takes pixels mapped to [-1, 1]
(mean 127.5, std 127.5), the landmark model (256 x 256 RGB) pixels mapped to [0, 1] (mean 0, std 255).
The network weights are not changed.
"""

import hashlib
import sys
import zipfile
from pathlib import Path

import mediapipe
from mediapipe.tasks.python.metadata.metadata_writers import metadata_writer
from mediapipe.tasks.python.metadata.metadata_writers.model_asset_bundle_utils import AlignZipFile

if mediapipe.__version__ != "0.10.21":
    sys.exit(f"needs mediapipe 0.10.21 (the version whose wheel bundles BlazePose), found {mediapipe.__version__}")

MODULES = Path(mediapipe.__file__).resolve().parent / "modules"
OUT = Path(__file__).resolve().parents[1] / "humotion" / "assets" / "capture" / "pose_landmarker_full.task"

# (bundle name, source model, model name, description, input mean, input std, output names)
MODELS = [
    (
        "pose_detector.tflite",
        MODULES / "pose_detection" / "pose_detection.tflite",
        "BlazePose detector",
        "Finds people (face-anchored boxes and 4 alignment keypoints) in a 224x224 RGB image.",
        127.5,
        127.5,
        ["raw boxes/keypoints", "scores"],
    ),
    (
        "pose_landmarks_detector.tflite",
        MODULES / "pose_landmark" / "pose_landmark_full.tflite",
        "BlazePose GHUM 3D landmarks (full)",
        "33 body landmarks, presence, segmentation, heatmap and world landmarks from a 256x256 RGB crop.",
        0.0,
        255.0,
        ["landmarks", "pose presence", "segmentation", "heatmap", "world landmarks"],
    ),
]


def with_metadata(model: bytes, name: str, description: str, mean: float, std: float, outputs: list[str]) -> bytes:
    """The model with (replaced) metadata: general info, RGB image input normalisation, named outputs."""
    writer = metadata_writer.MetadataWriter.create(bytearray(model))
    writer.add_general_info(name, description)
    writer.add_image_input(norm_mean=[mean], norm_std=[std])
    for output in outputs:
        writer.add_feature_output(name=output)
    tflite, _ = writer.populate()
    return bytes(tflite)


def main() -> None:
    bundle = {}
    for bundle_name, source, name, description, mean, std, outputs in MODELS:
        model = source.read_bytes()
        print(f"{source.relative_to(MODULES.parent)}: {len(model)} bytes, sha256 {hashlib.sha256(model).hexdigest()}")
        bundle[bundle_name] = with_metadata(model, name, description, mean, std, outputs)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    # What mediapipe's create_model_asset_bundle writes, with a fixed timestamp so the file is reproducible.
    with AlignZipFile(OUT, mode="w", alignment=4) as bundle_zip:
        for bundle_name, model in bundle.items():
            bundle_zip.writestr(zipfile.ZipInfo(bundle_name, date_time=(1980, 1, 1, 0, 0, 0)), model)
    print(f"wrote {OUT}: {OUT.stat().st_size} bytes, sha256 {hashlib.sha256(OUT.read_bytes()).hexdigest()}")


if __name__ == "__main__":
    main()
