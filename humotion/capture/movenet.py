"""Everyone in the frame, small people too: MoveNet MultiPose finds people, MoveNet Lightning follows each.

Two Google models (Apache-2.0; humotion/assets/capture/MODEL_CARD.md), shipped as ONNX and run by
onnxruntime on the CPU, offline (their padding folded into their convolutions at load, `folded_model`):

- MoveNet MultiPose Lightning (`movenet_multipose_256.onnx`, 256 x 256 input), a CenterNet: a
  heatmap of people's centres, and from each centre the 17 COCO keypoints. It scans square regions
  of the frame (`scan_regions`): the whole frame letterboxed, and tiles at the image's own
  resolution (256 px) and, on large frames, at twice that, so that a person from about 50 px tall
  up to the full frame is seen at a size the model knows. A person seen in two regions is merged
  (`merge_detections`).
- MoveNet SinglePose Lightning (`movenet_lightning_192.onnx`, 192 x 192) runs top-down on a square
  crop around one person's box (`detect_near`): the cheap per-person step that follows known people
  between scans, and that sharpens the keypoints of people a scan found.

`MoveNetDetector.detect` (one image: every region, then each person on their own crop) is a
`PoseDetector`. For video, `humotion.capture.follow.PeopleFinder` scans a few regions per frame in
turn and follows the tracker's people with `detect_near` in between.

Keypoints are COCO's 17 (the first 17 of `KEYPOINTS`); MoveNet has no heels or toes, so those get
confidence 0 (placed at the ankles). Confidence is MoveNet's keypoint heatmap score.

Decoding (the models ship without their own post-processing, see scripts/make_movenet_onnx.py),
as MoveNet's published graphs do it: centres are local maxima of the centre heatmap (MultiPose),
or its maximum weighted by closeness to the crop's centre (Lightning); each keypoint starts at the
centre plus its regressed offset, and moves to the keypoint heatmap's maximum weighted by
1 / (distance to that point + 1.8 cells), plus the sub-cell offset there.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from humotion.assets import ASSETS
from humotion.capture.detection import KEYPOINTS, MAX_PEOPLE, Detection, keypoint_box
from humotion.io.video import check_image

MULTIPOSE_PATH: Path = ASSETS / "capture" / "movenet_multipose_256.onnx"
"""MoveNet MultiPose Lightning, 256 x 256 input (ONNX, float16 weights)."""
LIGHTNING_PATH: Path = ASSETS / "capture" / "movenet_lightning_192.onnx"
"""MoveNet SinglePose Lightning v4, 192 x 192 input (ONNX, float16 weights)."""

_COCO = 17
_STRIDE = 4  # pixels of the model input per heatmap cell


@dataclass(frozen=True)
class Region:
    """A square part of the image: top-left corner (x0, y0) and side, pixels; it may reach past the
    image's border (that part is black). interior: whether it is a tile inside the frame (people
    cut by its edges are left to its neighbours) rather than the whole frame or a person's crop."""

    x0: float
    y0: float
    side: float
    interior: bool = False

    @classmethod
    def around(cls, box: Sequence[float], margin: float, min_side: float = 32.0) -> Region:
        """The square centred on box (x0, y0, x1, y1) whose side is margin times the box's longer side."""
        x0, y0, x1, y1 = box
        side = max(max(x1 - x0, y1 - y0) * margin, min_side)
        return cls((x0 + x1 - side) / 2, (y0 + y1 - side) / 2, side)


def scan_regions(width: int, height: int, tile: int = 256, overlap: float = 0.3) -> list[Region]:
    """The regions a full scan looks at: the whole frame, then overlapping square tiles.

    Tiles of `tile` pixels (the model's input size: no downscaling, for the smallest people) and of
    twice, four times ... that while smaller than 0.75 of the frame's shorter side. A frame too small
    for a tile of `tile` pixels gets tiles of 0.75 of its shorter side, enlarged to the model's input
    (a 320 x 240 video's people 45 px tall are seen 64 px tall). Neighbouring tiles overlap by
    `overlap` of their side.
    """
    regions = [Region(0.0, 0.0, float(max(width, height)))]
    sides = [min(float(tile), 0.75 * min(width, height))]
    while sides and 2 * sides[-1] < 0.75 * min(width, height):
        sides.append(2 * sides[-1])
    for side in sides:
        step = side * (1 - overlap)
        nx = max(1, math.ceil((width - side) / step) + 1)
        ny = max(1, math.ceil((height - side) / step) + 1)
        for y in np.linspace(0, max(height - side, 0), ny):
            for x in np.linspace(0, max(width - side, 0), nx):
                regions.append(Region(float(x), float(y), side, interior=True))
    return regions


def crop_region(image: np.ndarray, region: Region, size: int) -> np.ndarray:
    """(size, size, 3) uint8: the region of image resized to size, black where it leaves the image."""
    scale = size / region.side
    matrix = np.array([[scale, 0.0, -region.x0 * scale], [0.0, scale, -region.y0 * scale]])
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.warpAffine(image, matrix, (size, size), flags=interpolation, borderMode=cv2.BORDER_CONSTANT)


def box_iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1)."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    return inter / max((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter, 1e-9)


def same_person(a: Detection, b: Detection, tolerance: float = 0.15) -> bool:
    """Whether two detections are one person: their keypoints confident in both lie on average
    within tolerance times the person's size (the longer side of the larger box) of each other."""
    both = (a.confidence >= 0.2) & (b.confidence >= 0.2)
    if both.sum() < 4:
        return box_iou(a.box, b.box) > 0.6
    size = max(a.box[2] - a.box[0], a.box[3] - a.box[1], b.box[2] - b.box[0], b.box[3] - b.box[1], 1.0)
    distance = np.linalg.norm(a.keypoints[both] - b.keypoints[both], axis=1).mean()
    return bool(distance < tolerance * size)


def merge_detections(detections: Sequence[Detection], first: int = 0) -> list[Detection]:
    """The detections without duplicates of one person (`same_person`): the first `first` are kept
    as they are (e.g. people followed on their own crop), the rest best score first where they are
    no one already kept."""
    kept = list(detections[:first])
    for candidate in sorted(detections[first:], key=lambda d: -d.score):
        if not any(same_person(candidate, other) for other in kept):
            kept.append(candidate)
    return kept


def _session(path: Path, fold: bool = True):
    """An onnxruntime session of the model at path (fold: of `folded_model`), one thread."""
    import onnxruntime as ort  # imported here: only the MoveNet detector needs it

    model = folded_model(path).SerializeToString() if fold else str(_checked(path))
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # one thread per model: the video loop runs frame by frame
    options.inter_op_num_threads = 1
    return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])


def _checked(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"MoveNet model not found: {path}. It ships with humotion in humotion/assets/capture; "
                                "rebuild it with scripts/make_movenet_onnx.py (see its docstring) or reinstall humotion.")
    return path


def folded_model(path: Path):
    """The ONNX model at path, constants folded (onnxruntime's basic optimisations) and its padding
    folded into its convolutions (`fold_pads`): the same outputs, faster (the model card's Speed
    section)."""
    import tempfile

    import onnx
    import onnxruntime as ort

    _checked(path)
    with tempfile.TemporaryDirectory() as folder:  # constant folding first, so that the pads are constants
        options = ort.SessionOptions()
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        options.optimized_model_filepath = str(Path(folder) / "basic.onnx")
        ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        model = onnx.load(options.optimized_model_filepath)
    fold_pads(model.graph)
    return model


def fold_pads(graph) -> int:
    """graph (an onnx.GraphProto): fold each zero Pad of height and width (with constant pads) that feeds one Conv alone into
    that Conv's own pads, in place; returns how many were folded.

    The converter (scripts/make_movenet_onnx.py) writes TensorFlow's asymmetric "SAME" padding of
    the stride-2 convolutions as a Pad before a Conv (torch's conv2d pads symmetrically), which
    onnxruntime does not fuse: the Pad, and the layout changes around it, cost about a fifth of
    Lightning's time. ONNX's Conv takes asymmetric pads; the result is the same to the bit."""
    from onnx import helper, numpy_helper

    constants = {tensor.name: numpy_helper.to_array(tensor) for tensor in graph.initializer}
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    folded = []
    for node in graph.node:
        users = consumers.get(node.output[0], []) if node.op_type == "Pad" else []
        pads = constants.get(node.input[1]) if len(users) == 1 and users[0].op_type == "Conv" else None
        mode = {a.name: helper.get_attribute_value(a) for a in node.attribute}.get("mode", b"constant")
        value = constants.get(node.input[2]) if len(node.input) > 2 and node.input[2] else None
        if (pads is None or len(pads) != 8 or mode != b"constant" or (pads < 0).any() or pads[[0, 1, 4, 5]].any()
                or (value is not None and value.any()) or (len(node.input) > 3 and node.input[3])):
            continue
        conv = users[0]
        attributes = {a.name: helper.get_attribute_value(a) for a in conv.attribute}
        if attributes.get("auto_pad", b"NOTSET") != b"NOTSET":
            continue
        before = list(attributes.get("pads", [0, 0, 0, 0]))
        after = [before[0] + pads[2], before[1] + pads[3], before[2] + pads[6], before[3] + pads[7]]
        for attribute in [a for a in conv.attribute if a.name == "pads"]:
            conv.attribute.remove(attribute)
        conv.attribute.append(helper.make_attribute("pads", [int(v) for v in after]))
        conv.input[0] = node.input[0]
        folded.append(node)
    for node in folded:
        graph.node.remove(node)
    used = {name for node in graph.node for name in node.input}
    for tensor in [t for t in graph.initializer if t.name not in used]:  # the pads
        graph.initializer.remove(tensor)
    return len(folded)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


@functools.lru_cache(maxsize=4)
def _cells(grid: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(1, G * G) float64 row and column of every cell of a heatmap of shape grid."""
    ys, xs = np.mgrid[0:grid[0], 0:grid[1]]
    return ys.reshape(1, -1).astype(np.float64), xs.reshape(1, -1).astype(np.float64)


def decode_keypoints(heatmap: np.ndarray, regress: np.ndarray, offset: np.ndarray, cy: int, cx: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The 17 keypoints of the person centred on cell (cy, cx): ((17, 2) x, y in cells, (17,) scores).

    heatmap: (17, G, G) keypoint probabilities; regress, offset: (34, G, G) raw head outputs (y, x
    per keypoint)."""
    grid = heatmap.shape[1:]
    ys, xs = _cells(grid)
    start_y, start_x = cy + regress[0::2, cy, cx, None], cx + regress[1::2, cy, cx, None]  # (17, 1) cells
    distance = np.sqrt((ys - start_y) ** 2 + (xs - start_x) ** 2)                          # (17, G * G)
    best = (heatmap.reshape(_COCO, -1) / (distance + 1.8)).argmax(axis=1)
    by, bx = np.unravel_index(best, grid)
    k = np.arange(_COCO)
    y = by + offset[2 * k, by, bx]
    x = bx + offset[2 * k + 1, by, bx]
    return np.stack([x, y], axis=1), heatmap[k, by, bx]


class MoveNetDetector:
    """Several people per image with MoveNet (see the module docstring), CPU, offline.

    max_people: most people reported by `detect`.
    min_center: a MultiPose centre-heatmap peak needs this score to be a person.
    min_score: people whose mean keypoint score is below this are dropped.
    crop_margin: a person's crop is this many times the longer side of their keypoint box (the
        keypoints do not reach the top of the head or the soles).
    tile: pixels, the side of the smallest scan tiles (see `scan_regions`).
    fold: run the graphs with their padding folded into their convolutions (`folded_model`: the
        same outputs, faster); False runs the shipped graphs as they are (a baseline for
        bench/capture_speed.py).
    """

    name = "movenet"

    def __init__(self, max_people: int = MAX_PEOPLE, min_center: float = 0.2, min_score: float = 0.25,
                 crop_margin: float = 1.3, tile: int = 256, fold: bool = True):
        if max_people < 1 or not crop_margin >= 1 or tile < 64:
            raise ValueError(f"need max_people >= 1, crop_margin >= 1 and tile >= 64, got {max_people}, "
                             f"{crop_margin} and {tile}")
        self.max_people, self.min_center, self.min_score = max_people, min_center, min_score
        self.crop_margin, self.tile = crop_margin, tile
        self._multipose = _session(MULTIPOSE_PATH, fold)
        self._lightning = _session(LIGHTNING_PATH, fold)
        self._multipose_size = self._multipose.get_inputs()[0].shape[1]
        self._lightning_size = self._lightning.get_inputs()[0].shape[1]
        g = self._lightning_size // _STRIDE
        ys, xs = np.mgrid[0:g, 0:g]
        middle = (g - 1) / 2
        self._centre_weight = 1.0 / (np.sqrt((ys - middle) ** 2 + (xs - middle) ** 2) + 1.0)

    # -- one image ------------------------------------------------------------------------

    def detect(self, image: np.ndarray) -> list[Detection]:
        """People in image ((H, W, 3) uint8 RGB), in `KEYPOINTS` layout, best first; [] if none.

        Every scan region, then each person found again on a crop of their own."""
        image = check_image(image)
        found = self.detect_regions(image, scan_regions(image.shape[1], image.shape[0], self.tile))
        return sorted(self.refine(image, found), key=lambda d: -d.score)[: self.max_people]

    def detect_regions(self, image: np.ndarray, regions: Sequence[Region]) -> list[Detection]:
        """The people MultiPose finds in each region of image ((H, W, 3) uint8 RGB), keypoints
        (21, 2) in image pixels, duplicates merged. People cut by the inner edge of a tile are
        left out (a neighbouring tile or a larger region sees them whole)."""
        image = check_image(image)
        height, width = image.shape[:2]
        found = []
        for region in regions:
            found += [d for d in self._multipose_people(image, region)
                      if not (region.interior and _cut(d, region, width, height))]
        return merge_detections(found)

    def _multipose_people(self, image: np.ndarray, region: Region) -> list[Detection]:
        """The people MultiPose finds in one region, in image pixels."""
        size = self._multipose_size
        crop = crop_region(image, region, size).astype(np.int32)[None]
        center, heat, regress, offset = (o[0] for o in self._multipose.run(None, {"image": crop})[:4])
        center, heat = _sigmoid(center[0]), _sigmoid(heat)
        pooled = cv2.dilate(center, np.ones((5, 5), np.uint8))
        peaks = np.argwhere((center >= pooled) & (center >= self.min_center))
        peaks = peaks[np.argsort(-center[peaks[:, 0], peaks[:, 1]])][: 2 * self.max_people]
        found = []
        for cy, cx in peaks:
            cells, scores = decode_keypoints(heat, regress, offset, int(cy), int(cx))
            detection = self._detection(cells, scores, region, size)
            if detection is not None:
                found.append(detection)
        return found

    def refine(self, image: np.ndarray, detections: Sequence[Detection]) -> list[Detection]:
        """Each detection found again by Lightning on a crop of image ((H, W, 3) uint8 RGB) around
        it (sharper keypoints); the original where the crop finds nobody or someone else.
        Duplicates merged."""
        again = self.detect_near(image, [d.box for d in detections])
        out = [a if a is not None and same_person(a, d, 0.2) else d for a, d in zip(again, detections)]
        return merge_detections(out)

    # -- video: following known people ------------------------------------------------------

    def detect_near(self, image: np.ndarray, boxes: Sequence[Sequence[float]]) -> list[Detection | None]:
        """For each box (x0, y0, x1, y1 pixels: a keypoint box where a person is expected), that
        person in image ((H, W, 3) uint8 RGB), or None.

        Alone, the person is looked for by Lightning on a square crop around the box (the person
        nearest the crop's centre) and kept when their keypoint box overlaps the expected one (IoU
        0.5). For a group (boxes that overlap), or where Lightning finds no one or someone else,
        MultiPose runs once on a crop around the group and each box takes the person whose keypoint
        box overlaps it most (IoU 0.4 at least; larger boxes choose first): Lightning, made for one
        person, drifts onto a neighbour there."""
        image = check_image(image)
        size = self._lightning_size
        out: list[Detection | None] = [None] * len(boxes)
        groups = _groups(boxes)
        for group in groups:
            if len(group) == 1:
                box = boxes[group[0]]
                region = Region.around(box, self.crop_margin)
                crop = crop_region(image, region, size).astype(np.int32)[None]
                center, heat, regress, offset = (o[0] for o in self._lightning.run(None, {"image": crop}))
                weighted = _sigmoid(center[0]) * self._centre_weight
                cy, cx = np.unravel_index(int(weighted.argmax()), weighted.shape)
                cells, scores = decode_keypoints(_sigmoid(heat), regress, offset, int(cy), int(cx))
                found = self._detection(cells, scores, region, size)
                if found is not None and box_iou(found.box, box) >= 0.5:
                    out[group[0]] = found
                    continue  # else a neighbour in the crop, or a drift: not the person expected
            union = (min(boxes[i][0] for i in group), min(boxes[i][1] for i in group),
                     max(boxes[i][2] for i in group), max(boxes[i][3] for i in group))
            candidates = self._multipose_people(image, Region.around(union, 1.6 * self.crop_margin))
            taken: set[int] = set()
            for i in sorted(group, key=lambda i: -(boxes[i][3] - boxes[i][1])):  # larger (nearer) people first
                overlaps = [box_iou(c.box, boxes[i]) if k not in taken else 0.0 for k, c in enumerate(candidates)]
                if overlaps and max(overlaps) >= 0.4:
                    best = int(np.argmax(overlaps))
                    out[i] = candidates[best]
                    taken.add(best)
        return out

    def _detection(self, cells: np.ndarray, scores: np.ndarray, region: Region, size: int) -> Detection | None:
        """A Detection in image pixels from keypoints in heatmap cells of a size x size crop of region;
        None below min_score, for a body part alone (fewer than 6 keypoints of score 0.3, or
        neither both shoulders nor both hips among them), or for sure keypoints along a line."""
        score = float(scores.mean())
        sure = scores >= 0.3
        if score < self.min_score or sure.sum() < 6 or not (sure[5:7].all() or sure[11:13].all()):
            return None
        extent = np.ptp(cells[sure], axis=0)  # x, y cells
        if extent[0] < 0.15 * extent[1] or extent[1] < 0.15 * extent[0]:
            return None  # a line of points (a walking pole, a door frame), not a body
        pixels = cells * (_STRIDE * region.side / size) + np.array([region.x0, region.y0])
        keypoints = np.zeros((len(KEYPOINTS), 2), np.float32)
        confidence = np.zeros(len(KEYPOINTS), np.float32)
        keypoints[:_COCO], confidence[:_COCO] = pixels, np.clip(scores, 0.0, 1.0)
        keypoints[_COCO:] = keypoints[[15, 16, 15, 16]]  # heels and big toes: at the ankles, confidence 0
        return Detection(keypoints, confidence, score, keypoint_box(keypoints, confidence, 0.2))

    def close(self) -> None:
        """Nothing to free early (onnxruntime sessions go with the detector); for symmetry with
        MediaPipePoseDetector."""

    def __enter__(self) -> MoveNetDetector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _groups(boxes: Sequence[Sequence[float]]) -> list[list[int]]:
    """Indices of boxes in groups of overlapping ones (IoU over 0.05, chained)."""
    groups: list[list[int]] = []
    for i, box in enumerate(boxes):
        joined = [g for g in groups if any(box_iou(box, boxes[j]) > 0.05 for j in g)]
        merged = [i] + [j for g in joined for j in g]
        groups = [g for g in groups if g not in joined] + [sorted(merged)]
    return groups


def _cut(detection: Detection, region: Region, width: int, height: int, margin: float = 0.03) -> bool:
    """Whether a detection's confident keypoints reach an edge of the tile that lies inside the image."""
    x0, y0, x1, y1 = detection.box
    edge = margin * region.side
    return bool((x0 < region.x0 + edge and region.x0 > 0) or (y0 < region.y0 + edge and region.y0 > 0)
                or (x1 > region.x0 + region.side - edge and region.x0 + region.side < width)
                or (y1 > region.y0 + region.side - edge and region.y0 + region.side < height))
