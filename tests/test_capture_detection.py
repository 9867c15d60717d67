"""2D pose detection on real CC0 photos (../shared/data/images/yogait_cc0) and on bad input."""

from pathlib import Path

import numpy as np
import pytest

from humotion.capture import KEYPOINTS, Detection, MediaPipePoseDetector, PoseDetector, keypoint_box

PHOTOS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "images" / "yogait_cc0"
T_POSES = ["t_pose_t6.jpg", "t_pose_t_pose_test.png"]
STANDING = ["tadasana_tada1.jpg", "tadasana_tada3.jpg", "tadasana_tada4.jpg"]
K = {name: i for i, name in enumerate(KEYPOINTS)}


@pytest.fixture(scope="module")
def detector():
    with MediaPipePoseDetector() as detector:
        yield detector


def photo(name: str) -> np.ndarray:
    Image = pytest.importorskip("PIL.Image")
    path = PHOTOS / name
    if not path.is_file():
        pytest.skip(f"real photos not found at {PHOTOS}")
    return np.asarray(Image.open(path).convert("RGB"))


def only_person(detector, name: str) -> tuple[Detection, np.ndarray]:
    image = photo(name)
    people = detector.detect(image)
    assert len(people) == 1, f"{name}: {len(people)} people"
    person = people[0]
    assert person.keypoints.shape == (21, 2) and person.keypoints.dtype == np.float32
    assert person.confidence.shape == (21,) and person.confidence.dtype == np.float32
    assert ((person.confidence >= 0) & (person.confidence <= 1)).all()
    assert 0.5 < person.score <= 1
    x0, y0, x1, y1 = person.box
    assert 0 <= x0 < x1 <= image.shape[1] and 0 <= y0 < y1 <= image.shape[0]
    return person, image


def test_layout():
    assert len(KEYPOINTS) == 21 == len(set(KEYPOINTS))
    assert KEYPOINTS[:5] == ("nose", "left_eye", "right_eye", "left_ear", "right_ear")
    assert KEYPOINTS[15:] == ("left_ankle", "right_ankle", "left_heel", "right_heel", "left_big_toe", "right_big_toe")


def test_is_a_pose_detector(detector):
    assert isinstance(detector, PoseDetector)
    assert detector.name


@pytest.mark.parametrize("name", T_POSES)
def test_t_pose_arms_out_level_with_shoulders(detector, name):
    person, _ = only_person(detector, name)
    xy = person.keypoints
    shoulder_y = (xy[K["left_shoulder"], 1] + xy[K["right_shoulder"], 1]) / 2
    hip_y = (xy[K["left_hip"], 1] + xy[K["right_hip"], 1]) / 2
    torso = hip_y - shoulder_y
    assert torso > 0
    for side in ("left", "right"):
        wrist, hip = xy[K[f"{side}_wrist"]], xy[K[f"{side}_hip"]]
        assert person.confidence[K[f"{side}_wrist"]] > 0.8
        assert abs(wrist[1] - shoulder_y) < 0.35 * torso, f"{side} wrist not level with the shoulders"
        assert np.linalg.norm(wrist - hip) > 1.2 * torso, f"{side} wrist near the hip"
    # Facing the camera: the person's left is on the image's right, and each wrist is beyond its shoulder.
    assert xy[K["left_wrist"], 0] > xy[K["left_shoulder"], 0] + 0.5 * torso
    assert xy[K["right_wrist"], 0] < xy[K["right_shoulder"], 0] - 0.5 * torso


@pytest.mark.parametrize("name", STANDING)
def test_standing_body_is_upright(detector, name):
    person, image = only_person(detector, name)
    y = person.keypoints[:, 1]
    for side in ("left", "right"):
        chain = ["nose", f"{side}_shoulder", f"{side}_hip", f"{side}_knee", f"{side}_ankle"]
        assert all(y[K[a]] < y[K[b]] for a, b in zip(chain, chain[1:])), f"{side}: {[y[K[j]] for j in chain]}"
        assert (person.confidence[[K[j] for j in chain]] > 0.9).all()
    # The person fills most of the photo's height.
    assert min(y[K["left_ankle"]], y[K["right_ankle"]]) - y[K["nose"]] > 0.6 * image.shape[0]


# Keypoints that mediapipe 0.10.21's own legacy `solutions.pose.Pose(static_image_mode=True,
# model_complexity=1)` finds on tadasana_tada1.jpg (pixels), to check that the shipped bundle runs
# the same models with the same input normalisation. (A wrong normalisation moves points by ~1-5 px.)
REFERENCE_TADA1 = [
    (150.0, 76.3), (159.1, 66.0), (138.0, 67.0), (168.3, 69.5), (127.8, 72.4), (205.1, 147.4), (97.4, 145.7),
    (225.9, 232.5), (77.2, 233.8), (263.9, 304.0), (41.1, 304.3), (179.9, 302.9), (118.7, 303.4),
    (190.9, 429.6), (111.2, 431.0), (196.7, 544.2), (106.5, 544.7), (185.8, 562.6), (117.5, 562.6),
    (219.6, 582.3), (76.3, 580.6),
]  # fmt: skip


def test_matches_mediapipe_reference_graph(detector):
    person, _ = only_person(detector, "tadasana_tada1.jpg")
    error = np.linalg.norm(person.keypoints - np.array(REFERENCE_TADA1), axis=1)
    assert np.median(error) < 0.5 and error.max() < 2.0, error.round(2)


def test_several_people(detector):
    Image = pytest.importorskip("PIL.Image")
    images = []
    for name in STANDING:
        one = Image.fromarray(photo(name))
        images.append(np.asarray(one.resize((round(one.width * 480 / one.height), 480))))
    people = detector.detect(np.concatenate(images, axis=1))
    assert len(people) == 3
    centres = sorted((p.box[0] + p.box[2]) / 2 for p in people)
    edges = np.cumsum([im.shape[1] for im in images])
    assert centres[0] < edges[0] < centres[1] < edges[1] < centres[2]


def test_blank_image_has_nobody(detector):
    assert detector.detect(np.full((480, 640, 3), 128, np.uint8)) == []


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((480, 640), np.uint8),
        np.zeros((480, 640, 4), np.uint8),
        np.zeros((3, 480, 640), np.uint8),
        np.zeros((480, 640, 3), np.float32),
        np.zeros((0, 640, 3), np.uint8),
    ],
)
def test_bad_images_are_refused(detector, image):
    with pytest.raises(ValueError, match=str(image.dtype) if image.dtype != np.uint8 else r"shape \("):
        detector.detect(image)


def test_non_contiguous_image(detector):
    image = photo(STANDING[0])
    mirrored = detector.detect(image[:, ::-1])
    assert len(mirrored) == 1


def test_missing_model_names_file_and_fix(tmp_path):
    with pytest.raises(FileNotFoundError, match="make_pose_task.py") as error:
        MediaPipePoseDetector(model_path=tmp_path / "nope.task")
    assert "nope.task" in str(error.value)


def test_keypoint_box_ignores_unsure_points():
    keypoints = np.array([[10, 20], [30, 5], [1000, 1000]], np.float32)
    assert keypoint_box(keypoints, np.array([1, 0.9, 0.1], np.float32)) == (10, 5, 30, 20)
    assert keypoint_box(keypoints, np.zeros(3, np.float32)) == (10, 5, 1000, 1000)


# ---------------------------------------------------------------- MoveNet: everyone in the frame

MARKS = Path(__file__).resolve().parents[1] / "bench" / "data" / "people_marks.json"
VIDEO_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video"


@pytest.fixture(scope="module")
def movenet():
    from humotion.capture.movenet import MoveNetDetector

    with MoveNetDetector() as detector:
        yield detector


@pytest.fixture(scope="module")
def hikers():
    """{frame index: (RGB image, marked people boxes)} for three hand-marked frames of the hikers clip."""
    import json

    cv2 = pytest.importorskip("cv2")
    marks = json.loads(MARKS.read_text())["videos"]["hikers"]
    path = VIDEO_DIR / Path(marks["path"]).name
    if not path.is_file():
        pytest.skip(f"real footage not found at {path}")
    wanted = {180: None, 300: None, 420: None}
    capture, index = cv2.VideoCapture(str(path)), 0
    while index <= max(wanted):
        ok, bgr = capture.read()
        assert ok, f"{path} ended at frame {index}"
        if index in wanted:
            wanted[index] = (cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), marks["frames"][str(index)]["people"])
        index += 1
    return wanted


@pytest.mark.parametrize("frame", [180, 300, 420])
def test_movenet_finds_every_marked_hiker(movenet, hikers, frame):
    from humotion.capture.detection import body_box
    from humotion.capture.movenet import box_iou

    image, marked = hikers[frame]
    people = movenet.detect(image)
    assert len(people) >= len(marked)
    boxes = [body_box(p.keypoints, p.confidence) for p in people]
    for mark in marked:  # 3 to 5 people, 110 to 440 px tall, side by side and overlapping
        assert max(box_iou(mark, b) for b in boxes) >= 0.5, f"frame {frame}: nobody at {mark}"
    for person in people:
        assert person.keypoints.shape == (21, 2) and person.confidence.shape == (21,)
        assert (person.confidence[17:] == 0).all()  # MoveNet has no heels or toes


@pytest.mark.parametrize("name", ["LIGHTNING_PATH", "MULTIPOSE_PATH"])
def test_movenet_sessions_fold_the_padding_and_give_the_shipped_models_outputs(hikers, name):
    import onnx
    import onnxruntime as ort

    from humotion.capture import movenet as module

    path = getattr(module, name)
    raw = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    size = raw.get_inputs()[0].shape[1]
    image, marked = hikers[300]
    crop = module.crop_region(image, module.Region.around(marked[0], 1.3), size).astype(np.int32)[None]
    for expected, got in zip(raw.run(None, {"image": crop}), module._session(path).run(None, {"image": crop})):
        np.testing.assert_allclose(got, expected, atol=1e-4)  # the same arithmetic: in practice equal to the bit
    assert sum(n.op_type == "Pad" for n in onnx.load(path).graph.node) == 5  # the stride-2 convolutions' "SAME" padding
    assert not any(n.op_type == "Pad" for n in module.folded_model(path).graph.node)


def test_movenet_is_a_pose_detector_and_sees_nobody_in_a_blank_image(movenet):
    assert isinstance(movenet, PoseDetector) and movenet.name == "movenet"
    assert movenet.detect(np.full((480, 640, 3), 128, np.uint8)) == []


def test_movenet_follows_a_person_from_their_box(movenet, hikers):
    image, marked = hikers[300]
    people = movenet.detect(image)
    again = movenet.detect_near(image, [p.box for p in people])
    agreeing = 0
    for before, after in zip(people, again):
        if after is not None:
            both = (before.confidence > 0.5) & (after.confidence > 0.5)
            agreeing += np.median(np.linalg.norm(before.keypoints[both] - after.keypoints[both], axis=1)) < 10
    assert agreeing >= len(marked)  # each marked hiker found again on the crop around their box


def test_scan_regions_cover_the_frame_with_small_and_whole_views():
    from humotion.capture.movenet import scan_regions

    for width, height, smallest in ((640, 480, 256), (1280, 720, 256), (480, 270, 202.5), (320, 240, 180)):
        regions = scan_regions(width, height)      # small frames: tiles of 0.75 of the shorter side, enlarged
        assert regions[0].side == max(width, height) and not regions[0].interior
        tiles = [r for r in regions if r.interior]
        assert min(r.side for r in tiles) == smallest
        covered = np.zeros((height, width), bool)
        for r in tiles:
            if r.side == smallest:
                covered[int(r.y0):int(r.y0 + r.side), int(r.x0):int(r.x0 + r.side)] = True
        assert covered.all()


def test_duplicates_of_one_person_are_merged():
    from humotion.capture.movenet import merge_detections

    keypoints = np.random.default_rng(0).uniform(100, 300, (21, 2)).astype(np.float32)
    confidence = np.full(21, 0.9, np.float32)
    a = Detection(keypoints, confidence, 0.8, keypoint_box(keypoints, confidence))
    b = Detection(keypoints + 3, confidence, 0.9, keypoint_box(keypoints + 3, confidence))
    c = Detection(keypoints + 400, confidence, 0.7, keypoint_box(keypoints + 400, confidence))
    merged = merge_detections([a, b, c])
    assert [d.score for d in merged] == [0.9, 0.7]
    assert merge_detections([a, b, c], first=1)[0] is a


def test_unknown_detector_names_the_choices():
    from humotion.capture.follow import make_detector

    with pytest.raises(ValueError, match="movenet, mediapipe"):
        make_detector("yolo")


def test_tfjs_graph_reader_matches_tensorflow_same_padding_and_float16_weights(tmp_path):
    """A one-node TF.js graph (a strided SAME convolution with fused bias and ReLU6; its bias stored
    as float16) against the convolution written out in numpy with TensorFlow's padding rule."""
    import base64
    import json

    import torch

    from humotion.capture.tfjs_graph import TFJSGraph

    rng = np.random.default_rng(0)
    kernel = rng.normal(size=(3, 3, 3, 4)).astype(np.float32)           # HWIO
    bias = rng.normal(size=4).astype(np.float16)
    (tmp_path / "w.bin").write_bytes(kernel.tobytes() + bias.tobytes())

    def text(value):
        return {"s": base64.b64encode(value.encode()).decode()}

    nodes = [
        {"name": "x", "op": "Placeholder"},
        {"name": "k", "op": "Const"}, {"name": "b", "op": "Const"},
        {"name": "y", "op": "_FusedConv2D", "input": ["x", "k", "b"],
         "attr": {"strides": {"list": {"i": ["1", "2", "2", "1"]}}, "padding": text("SAME"),
                  "fused_ops": {"list": {"s": [text("BiasAdd")["s"], text("Relu6")["s"]]}}}},
    ]
    manifest = [{"paths": ["w.bin"], "weights": [
        {"name": "k", "shape": [3, 3, 3, 4], "dtype": "float32"},
        {"name": "b", "shape": [4], "dtype": "float32", "quantization": {"dtype": "float16"}}]}]
    (tmp_path / "model.json").write_text(json.dumps({"modelTopology": {"node": nodes}, "weightsManifest": manifest}))
    image = rng.normal(size=(1, 5, 6, 3)).astype(np.float32)
    got = TFJSGraph(tmp_path / "model.json", ["y"])(torch.from_numpy(image))["y"][0].permute(1, 2, 0).numpy()

    padded = np.pad(image[0], ((1, 1), (0, 1), (0, 0)))  # TF SAME: height 5 -> (1, 1), width 6 -> (0, 1)
    expected = np.zeros((3, 3, 4), np.float32)
    for i in range(3):
        for j in range(3):
            expected[i, j] = np.einsum("hwc,hwco->o", padded[2 * i:2 * i + 3, 2 * j:2 * j + 3], kernel)
    expected = np.clip(expected + bias.astype(np.float32), 0, 6)
    assert got.shape == (3, 3, 4)
    assert np.abs(got - expected).max() < 1e-4
