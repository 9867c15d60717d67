"""People found and followed on real multi-person footage, against people marked by hand.

    .venv/bin/python bench/capture_people.py [--detector movenet|mediapipe] [--videos hikers aisle room]
                                             [--scan-interval 0.1 0.3] [--detect-every 1 2]
                                             [--scale 0.5] [--step 3] [--mosaic 2] [--max-people 10 20]
                                             [--show-ids] [--stills]
                                             [--overlay FRAME --overlay-out PNG]

The clips are ../shared/data/video (see SOURCE.md there); the marks are bench/data/people_marks.json:
boxes drawn by hand around every person on a few frames of each clip ("people"), and around people
mostly hidden or cut by the border ("ignore": finding them counts neither way).

Each clip is run through the video path of `humotion capture` (humotion.capture.follow.PeopleFinder:
the detector, top-down where it can, and the tracker), one thread. On every marked frame:

- a person found matches a mark when the IoU of their body box (humotion.capture.detection.body_box:
  the keypoint box grown to the head top, soles and hands) with the mark is at least 0.5, one to one
  (Hungarian on IoU);
- recall: marks matched / marks; false positives: people found matching neither a mark nor an
  ignored box (IoU < 0.3 with all);
- ids: each mark names its person ("who"); for every person found on two or more marked frames,
  the number of different ids they were given across the clip (1 is right), and id switches (a
  person's id differing from the one on the last marked frame they were found on), and shared
  ids: ids given to two or more marked people over the clip (an id passed from one person to
  another, which the switch count sees on the first person only).

Settings, each run side by side with the others given:
- --scan-interval S ...: seconds between scans while someone is followed (PeopleFinder's
  scan_interval); one run per value.
- --detect-every K ...: the pose model on every K-th frame per person, optical flow in between
  (PeopleFinder's detect_every; 1 is the model on every frame, the default's baseline); one run
  per value.
- --step N: every N-th frame only, the clip as a camera at 1/N of its frame rate films it (the
  hikers at 10 fps with --step 3); marks on the frames dropped are not scored.
- --scale F: every frame resized by F (smaller people: the hikers at 0.5 are 45-225 px tall in a
  320 x 240 frame); found boxes are scaled back to the marks.
- --mosaic N: N x N copies of the clip side by side in one frame, each cell running a different
  stretch of it (cell q starts q marking intervals later, the clip played forwards and backwards
  when it ends) and every other cell mirrored: a crowd of small people from real footage (the
  hikers at --scale 0.5 --mosaic 2: 640 x 480 frames, 17-24 marked people 45-150 px tall). A frame is
  scored when every cell shows a marked frame; the same hiker in two cells counts as two people.
- --max-people N ...: most people followed at once (humotion capture's default); one run per value.
- --show-ids: each marked person's ids on the marked frames, to see where ids switch.
- --stills: also the detector alone on each marked frame (`detect`: every scan region at once),
  the recall a single image gets.

Speed: milliseconds per frame of following (crops), scanning (regions) and tracking, and frames
per second over the clip.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from humotion.capture.detection import body_box
from humotion.capture.follow import DETECT_EVERY, DETECTORS, SCAN_INTERVAL, PeopleFinder, make_detector
from humotion.capture.movenet import box_iou
from humotion.capture.people import PeopleTracker
from humotion.capture.pipeline import CaptureConfig

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MARKS = ROOT / "bench" / "data" / "people_marks.json"


def load_marks(path: Path = MARKS) -> dict:
    """{video name: {"path": Path, "frames": {index: {"people": [...], "ignore": [...]}}}}."""
    marks = json.loads(path.read_text())["videos"]
    return {name: {"path": DATA / v["path"], "frames": {int(k): f for k, f in v["frames"].items()}}
            for name, v in marks.items()}


def read_frames(path: Path):
    """(index, RGB image) of every frame of a video (OpenCV, as humotion.io.video decodes them)."""
    capture = cv2.VideoCapture(str(path))
    index = 0
    while True:
        ok, bgr = capture.read()
        if not ok:
            break
        yield index, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        index += 1
    capture.release()


def match(marks: list, boxes: list, threshold: float = 0.5) -> dict[int, int]:
    """{mark index: box index} one to one, IoU >= threshold (Hungarian on IoU)."""
    if not marks or not boxes:
        return {}
    iou = np.array([[box_iou(m, b) for b in boxes] for m in marks])
    rows, cols = linear_sum_assignment(-iou)
    return {int(r): int(c) for r, c in zip(rows, cols) if iou[r, c] >= threshold}


def score_frame(marked: dict, boxes: list) -> tuple[int, int, int, dict[int, int]]:
    """(marks, matched, false positives, {mark: box}) for one frame's found body boxes."""
    pairs = match(marked["people"], boxes)
    others = marked["people"] + marked["ignore"]
    false = sum(1 for j, b in enumerate(boxes)
                if j not in pairs.values() and max([box_iou(o, b) for o in others] + [0.0]) < 0.3)
    return len(marked["people"]), len(pairs), false, pairs


def mosaic_frames(video: dict, cells: int, scale: float = 1.0):
    """(index, RGB image, marks or None): cells x cells copies of the clip in one frame, each scaled.

    Cell q (row-major) shows frame q * spacing + index of the clip played forwards then backwards
    (spacing: the marked frames' common interval), mirrored when q is odd. Marks (in the clip's
    pixels, as the clip's own) exist when every cell shows a marked frame; "who" names gain the cell.
    """
    clip = [cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale != 1.0 else image
            for _, image in read_frames(video["path"])]
    height, width = clip[0].shape[:2]
    spacing = int(np.gcd.reduce(sorted(video["frames"])))
    period = 2 * (len(clip) - 1)

    def shown(t: int) -> int:
        t %= period
        return t if t < len(clip) else period - t

    cell_width, cell_height = width / scale, height / scale       # a cell in the marks' pixels

    def placed(box, q: int) -> list[float]:
        """A mark of the clip moved into cell q (mirrored when q is odd)."""
        left, top, right, bottom = box
        if q % 2:
            left, right = cell_width - right, cell_width - left
        x0, y0 = (q % cells) * cell_width, (q // cells) * cell_height
        return [left + x0, top + y0, right + x0, bottom + y0]

    for index in range(len(clip)):
        sources = [shown(index + q * spacing) for q in range(cells * cells)]
        views = [clip[s][:, ::-1] if q % 2 else clip[s] for q, s in enumerate(sources)]
        image = np.concatenate([np.concatenate(views[r * cells:(r + 1) * cells], axis=1) for r in range(cells)], axis=0)
        marks = None
        if all(s in video["frames"] for s in sources):
            marks = {"people": [], "ignore": [], "who": []}
            for q, s in enumerate(sources):
                marked = video["frames"][s]
                marks["people"] += [placed(b, q) for b in marked["people"]]
                marks["ignore"] += [placed(b, q) for b in marked["ignore"]]
                marks["who"] += [f"{who} @{q}" for who in marked["who"]]
        yield index, np.ascontiguousarray(image), marks


def clip_frames(video: dict, scale: float = 1.0):
    """(index, RGB image, marks or None) of the clip, each frame scaled."""
    for index, image in read_frames(video["path"]):
        if scale != 1.0:
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        yield index, image, video["frames"].get(index)


def run_video(name: str, video: dict, detector, regions_per_frame: int, scan_interval: float = SCAN_INTERVAL,
              detect_every: int = DETECT_EVERY, step: int = 1, scale: float = 1.0, mosaic: int = 1,
              max_people: int = CaptureConfig.max_people) -> dict:
    """Follow everyone through one clip (or a mosaic of it); score the marked frames; time the stages."""
    finder = PeopleFinder(detector, PeopleTracker(), regions_per_frame=regions_per_frame, scan_interval=scan_interval,
                          detect_every=detect_every, max_people=max_people)
    fps = cv2.VideoCapture(str(video["path"])).get(cv2.CAP_PROP_FPS) or 30.0
    totals = {"marks": 0, "found": 0, "false": 0}
    identities: dict[str, list] = {}   # marked person -> their id on each marked frame (None: not found)
    frames, wall = 0, 0.0
    source = mosaic_frames(video, mosaic, scale) if mosaic > 1 else clip_frames(video, scale)
    for index, image, marked in source:
        if index % step:
            continue
        start = time.perf_counter()
        people = finder(image, index / fps)
        wall += time.perf_counter() - start
        frames += 1
        if marked is None:
            continue
        boxes = [tuple(v / scale for v in body_box(p.detection.keypoints, p.detection.confidence)) for p in people]
        count, found, false, pairs = score_frame(marked, boxes)
        totals["marks"] += count
        totals["found"] += found
        totals["false"] += false
        for m, who in enumerate(marked["who"]):
            identities.setdefault(who, []).append(people[pairs[m]].id if m in pairs else None)
    switches = 0
    for ids in identities.values():
        found = [i for i in ids if i is not None]
        switches += sum(1 for a, b in zip(found, found[1:]) if a != b)
    ids_per_person = [len({i for i in ids if i is not None}) for ids in identities.values()
                      if sum(i is not None for i in ids) > 1]
    people_per_id: dict[int, set] = {}
    for who, ids in identities.items():
        for i in ids:
            if i is not None:
                people_per_id.setdefault(i, set()).add(who)
    shared = sum(1 for people in people_per_id.values() if len(people) > 1)
    timings = {k: 1e3 * v / max(finder.frames, 1) for k, v in finder.timings.items()}
    return {"video": name, **totals, "recall": totals["found"] / max(totals["marks"], 1), "switches": switches,
            "shared_ids": shared,
            "people_found_on_2+_frames": len(ids_per_person),
            "mean_ids_per_person": float(np.mean(ids_per_person)) if ids_per_person else float("nan"),
            "frames": frames, "fps": frames / wall, "ms": timings, "identities": identities}


def run_stills(name: str, video: dict, detector) -> dict:
    """The detector alone (every region of one image) on each marked frame."""
    totals = {"marks": 0, "found": 0, "false": 0}
    wall, count = 0.0, 0
    for index, image in read_frames(video["path"]):
        marked = video["frames"].get(index)
        if marked is None:
            continue
        start = time.perf_counter()
        people = detector.detect(image)
        wall += time.perf_counter() - start
        count += 1
        boxes = [body_box(p.keypoints, p.confidence) for p in people]
        marks, found, false, _ = score_frame(marked, boxes)
        totals["marks"] += marks
        totals["found"] += found
        totals["false"] += false
    return {"video": name, **totals, "recall": totals["found"] / max(totals["marks"], 1),
            "ms_per_image": 1e3 * wall / max(count, 1)}


def save_overlay(video: dict, detector, frame: int, out: Path, regions_per_frame: int, scan_interval: float = SCAN_INTERVAL) -> None:
    """The overlay (skeletons and ids, as in overlay.mp4) of one frame, after following the clip up to it."""
    from humotion.capture.overlay import draw_people

    finder = PeopleFinder(detector, PeopleTracker(), regions_per_frame=regions_per_frame, scan_interval=scan_interval)
    fps = cv2.VideoCapture(str(video["path"])).get(cv2.CAP_PROP_FPS) or 30.0
    for index, image in read_frames(video["path"]):
        people = finder(image, index / fps)
        if index == frame:
            out.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out), cv2.cvtColor(draw_people(image, people), cv2.COLOR_RGB2BGR))
            return


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--detector", choices=DETECTORS, default="movenet")
    parser.add_argument("--videos", nargs="*", default=None, help="names in the marks file (default: all)")
    parser.add_argument("--regions-per-frame", type=int, default=1)
    parser.add_argument("--scan-interval", type=float, nargs="+", default=[SCAN_INTERVAL],
                        help="seconds between scans; one run per value")
    parser.add_argument("--detect-every", type=int, nargs="+", default=sorted({1, DETECT_EVERY}),
                        help="the pose model on every k-th frame per person; one run per value (default: 1 and the default)")
    parser.add_argument("--step", type=int, default=1, help="every N-th frame only (a lower frame rate)")
    parser.add_argument("--scale", type=float, default=1.0, help="frames resized by this factor (smaller people)")
    parser.add_argument("--max-people", type=int, nargs="+", default=[CaptureConfig.max_people],
                        help="most people followed at once (default: humotion capture's); one run per value")
    parser.add_argument("--mosaic", type=int, default=1, help="N x N shifted copies of each clip in one frame (a crowd)")
    parser.add_argument("--show-ids", action="store_true", help="list each marked person's ids on the marked frames")
    parser.add_argument("--stills", action="store_true", help="also the detector alone on the marked frames")
    parser.add_argument("--overlay", type=int, metavar="FRAME", help="write the hikers overlay of this frame")
    parser.add_argument("--overlay-out", type=Path, default=ROOT / "docs" / "images" / "capture_people.png")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    marks = load_marks()
    if not all(v["path"].is_file() for v in marks.values()):
        print(f"footage not found under {DATA / 'video'}", file=sys.stderr)
        return 1
    detector = make_detector(args.detector, max(args.max_people))
    if args.overlay is not None:
        save_overlay(marks["hikers"], detector, args.overlay, args.overlay_out, args.regions_per_frame,
                     args.scan_interval[0])
        print(f"wrote {args.overlay_out}")
        return 0
    names = args.videos or list(marks)
    for scan_interval, detect_every, max_people in itertools.product(args.scan_interval, args.detect_every,
                                                                      args.max_people):
        rows = [run_video(name, marks[name], detector, args.regions_per_frame, scan_interval, detect_every, args.step,
                          args.scale, args.mosaic, max_people)
                for name in names]
        print(f"detector {args.detector}, regions per frame {args.regions_per_frame}, scan every {scan_interval} "
              f"s, pose model every {detect_every} frames per person"
              + (f", one frame in {args.step} of the clip" if args.step > 1 else "")
              + (f", frames scaled by {args.scale}" if args.scale != 1.0 else "")
              + (f", {args.mosaic} x {args.mosaic} mosaic" if args.mosaic > 1 else "")
              + f", at most {max_people} people; match: body box IoU >= 0.5")
        print("video    marks found recall  false-pos  id-switches  shared ids  people(found 2+)   ids/person  frames   "
              "fps  ms follow / scan / track")
        for r in rows:
            print(f"{r['video']:8s} {r['marks']:5d} {r['found']:5d} {100 * r['recall']:5.1f}%  {r['false']:9d}  "
                  f"{r['switches']:11d}  {r['shared_ids']:10d}  {r['people_found_on_2+_frames']:17d}  {r['mean_ids_per_person']:10.2f}  "
                  f"{r['frames']:6d} {r['fps']:5.1f}  {r['ms']['follow']:.1f} / {r['ms']['scan']:.1f} / {r['ms']['track']:.1f}")
            if args.show_ids:
                for who, ids in r["identities"].items():
                    print(f"    {who:28s} ids on its marked frames: {' '.join('-' if i is None else str(i) for i in ids)}")
        marks_all, found_all = sum(r["marks"] for r in rows), sum(r["found"] for r in rows)
        print(f"all      {marks_all:5d} {found_all:5d} {100 * found_all / max(marks_all, 1):5.1f}%  "
              f"{sum(r['false'] for r in rows):9d}  {sum(r['switches'] for r in rows):11d}  "
              f"{sum(r['shared_ids'] for r in rows):10d}")
    if args.stills:
        print("stills (detector alone, every region):")
        for name in names:
            s = run_stills(name, marks[name], detector)
            print(f"{name:8s} {s['marks']:5d} {s['found']:5d} {100 * s['recall']:5.1f}%  {s['false']:9d}  "
                  f"{s['ms_per_image']:.0f} ms per image")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
