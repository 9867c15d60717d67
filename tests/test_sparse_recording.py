"""Headset recording files: axes conventions, hand frames, round trips and clear errors."""

import json
import math

import pytest
import torch

from humotion import rotations as rot
from humotion.canonical import canonical_skeleton
from humotion.io.errors import MotionFileError
from humotion.motion import Motion
from humotion.sparse.recording import COLUMNS, HeadsetStream, read_recording, stream_from_motion, write_recording

FORWARD = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # humotion: the user faces +Z
LEFT = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)     # humotion: the left is +X


def yaw_quat(degrees: float) -> list[float]:
    """(w, x, y, z) rotation about +Y by an angle (right-handed: +Z turns towards +X)."""
    h = math.radians(degrees) / 2
    return [math.cos(h), 0.0, math.sin(h), 0.0]


def write_csv(path, rows, columns=COLUMNS):
    lines = [",".join(columns)] + [",".join("" if v is None else str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def frame(t=0.0, head_p=(0, 1.6, 0), head_q=(1, 0, 0, 0), left=((-0.3, 1.2, -0.4), (1, 0, 0, 0)), right=None):
    row = [t, *head_p, *head_q]
    for hand in (left, right):
        row += [0] + [None] * 7 if hand is None else [1, *hand[0], *hand[1]]
    return row


def test_openxr_axes(tmp_path):
    # Identity orientation looks along -Z in OpenXR; the left hand is at -X (X is right), in front at -Z.
    stream = read_recording(write_csv(tmp_path / "a.csv", [frame()]), convention="openxr")
    assert torch.allclose(stream.head_rotations[0] @ FORWARD, FORWARD)
    hand = stream.left_positions[0]
    assert hand[0] > 0.29 and hand[2] > 0.39 and hand[1] == pytest.approx(1.2)
    assert stream.visible.tolist() == [[True, False]] and torch.isnan(stream.right_positions).all()
    # A head yawed 90 deg to the left: about +Y in OpenXR (-Z turns towards -X, the left).
    stream = read_recording(write_csv(tmp_path / "b.csv", [frame(head_q=yaw_quat(90))]), convention="openxr")
    assert torch.allclose(stream.head_rotations[0] @ FORWARD, LEFT, atol=1e-9)


def test_unity_axes(tmp_path):
    # Unity: left-handed, +Z forward, X right; a positive yaw turns right, so -90 deg is left.
    rows = [frame(left=((-0.3, 1.2, 0.4), (1, 0, 0, 0))), frame(1 / 60, head_q=yaw_quat(-90))]
    stream = read_recording(write_csv(tmp_path / "u.csv", rows), convention="unity")
    assert torch.allclose(stream.head_rotations[0] @ FORWARD, FORWARD)
    hand = stream.left_positions[0]
    assert hand[0] > 0.29 and hand[2] > 0.39
    assert torch.allclose(stream.head_rotations[1] @ FORWARD, LEFT, atol=1e-9)
    assert stream.fps == pytest.approx(60)


def test_humotion_axes_and_hand_frames(tmp_path):
    stream = read_recording(write_csv(tmp_path / "h.csv", [frame(head_q=yaw_quat(90), left=((0.3, 1.2, 0.4), (1, 0, 0, 0)))]),
                            convention="humotion")
    assert torch.allclose(stream.head_rotations[0] @ FORWARD, LEFT, atol=1e-9)
    assert torch.allclose(stream.left_positions[0], torch.tensor([0.3, 1.2, 0.4], dtype=torch.float64))
    # 'forward' hand frame: identity = hand pointing forward, so the canonical left wrist's
    # finger axis (+X in its T-pose) points forward; 'tpose': identity is the T-pose.
    for convention, hand in (("openxr", (-0.3, 1.2, -0.4)), ("unity", (-0.3, 1.2, 0.4))):
        path = write_csv(tmp_path / f"f_{convention}.csv", [frame(left=(hand, (1, 0, 0, 0)), right=(hand, (1, 0, 0, 0)))])
        forward = read_recording(path, convention, hand_frame="forward")
        assert torch.allclose(forward.left_rotations[0] @ LEFT, FORWARD, atol=1e-9)
        assert torch.allclose(forward.right_rotations[0] @ -LEFT, FORWARD, atol=1e-9)
        tpose = read_recording(path, convention)
        assert torch.allclose(tpose.left_rotations[0], torch.eye(3, dtype=torch.float64))


def moving_stream() -> HeadsetStream:
    """A T-pose bringing both arms forward (into view in HT) while the body drifts and twists."""
    skeleton = canonical_skeleton(1.75)
    ramp = torch.linspace(0, 1, 12)[:, None, None]
    angles = ramp * torch.randn(1, 22, 3, generator=torch.Generator().manual_seed(3)) * 10
    for side, sign in (("left", -1), ("right", 1)):
        angles[:, skeleton.index(f"{side}_shoulder"), 1] += sign * 90 * ramp[:, 0, 0]
    root = torch.tensor([0.0, 0.95, 0.0]) + torch.linspace(0, 1, 12)[:, None] * torch.tensor([0.5, 0.0, 1.0])
    motion = Motion(skeleton, rot.euler_to_quat("XYZ", angles), root, fps=30.0)
    return stream_from_motion(motion, "HT")


@pytest.mark.parametrize("suffix", [".csv", ".json"])
@pytest.mark.parametrize("convention", ["openxr", "unity", "humotion"])
@pytest.mark.parametrize("hand_frame", ["tpose", "forward"])
def test_round_trip(tmp_path, suffix, convention, hand_frame):
    stream = moving_stream()
    path = tmp_path / f"rec{suffix}"
    write_recording(stream, path, convention=convention, hand_frame=hand_frame)
    back = read_recording(path, convention=convention, hand_frame=hand_frame)
    assert torch.equal(back.visible, stream.visible)
    for name in ("timestamps", "head_rotations", "head_positions", "left_rotations", "left_positions",
                 "right_rotations", "right_positions"):
        a, b = getattr(stream, name), getattr(back, name)
        assert torch.equal(torch.isnan(a), torch.isnan(b)), name
        assert torch.allclose(a.nan_to_num(), b.nan_to_num(), atol=1e-6), name
    if suffix == ".json":  # the file remembers its axes
        assert torch.allclose(read_recording(path).head_positions, stream.head_positions, atol=1e-9)


def test_stream_from_motion_and_signals():
    stream = moving_stream()
    assert len(stream) == 12 and stream.fps == pytest.approx(30)
    assert stream.visible.any() and not stream.visible.all()   # HT: some frames out of view
    hidden = ~stream.visible[:, 0]
    assert torch.isnan(stream.left_positions[hidden]).all() and torch.isfinite(stream.left_positions[~hidden]).all()
    s = stream.signals()
    for value in s.values():
        assert torch.isfinite(value).all() and value.shape[0] == 12
    assert (s["left"][hidden] == 0).all()
    mc = stream_from_motion(Motion.rest(canonical_skeleton(), 3), "MC")
    assert mc.visible.all() and mc.head_positions[0, 1] == pytest.approx(0.936 * 1.70, abs=1e-4)


def expect_error(path, *words):
    with pytest.raises(MotionFileError) as info:
        read_recording(path)
    message = str(info.value)
    assert str(path) in message and all(w in message for w in words), message
    return message


def test_bad_files(tmp_path):
    good = frame()
    expect_error(write_csv(tmp_path / "cols.csv", [good[:-1]], COLUMNS[:-1]), "missing columns", "right_qz")
    expect_error(write_csv(tmp_path / "head.csv", [good[:1] + good[4:]], COLUMNS[:1] + COLUMNS[4:]), "head_px")
    nan_head = frame(1.0)
    nan_head[2] = "nan"
    expect_error(write_csv(tmp_path / "nan.csv", [good, nan_head]), "line 3", "head pose")
    expect_error(write_csv(tmp_path / "time.csv", [frame(0.5), frame(0.5)]), "line 3", "timestamp")
    expect_error(write_csv(tmp_path / "text.csv", [frame("soon")]), "line 2", "not a number")
    part_pose = frame()
    part_pose[10] = None
    expect_error(write_csv(tmp_path / "hand.csv", [part_pose]), "line 2", "left hand", "visible")
    flag = frame()
    flag[8] = "maybe"
    expect_error(write_csv(tmp_path / "flag.csv", [flag]), "left_visible")
    expect_error(write_csv(tmp_path / "quat.csv", [frame(head_q=(0, 0, 0, 0))]), "quaternion")
    (tmp_path / "fields.csv").write_text(",".join(COLUMNS) + "\n1,2,3\n")
    expect_error(tmp_path / "fields.csv", "line 2", "fields")
    (tmp_path / "empty.csv").write_text("")
    expect_error(tmp_path / "empty.csv", "empty")
    expect_error(write_csv(tmp_path / "header.csv", []), "no frames")
    (tmp_path / "list.json").write_text(json.dumps([1, 2]))
    expect_error(tmp_path / "list.json", "frames")
    (tmp_path / "item.json").write_text(json.dumps({"frames": [dict(zip(COLUMNS, frame())), 3]}))
    expect_error(tmp_path / "item.json", "frame 1")
    (tmp_path / "broken.json").write_text('{"frames": [\n{"timestamp": 0,}]}')
    expect_error(tmp_path / "broken.json", "line 2", "invalid JSON")
    (tmp_path / "axes.json").write_text(json.dumps({"convention": "unity", "frames": [dict(zip(COLUMNS, frame()))]}))
    with pytest.raises(MotionFileError, match="declares convention"):
        read_recording(tmp_path / "axes.json", convention="openxr")
    assert read_recording(tmp_path / "axes.json").left_positions[0, 2] < 0   # unity: -0.4 is behind
    expect_error(tmp_path / "missing.csv", "cannot read")
    with pytest.raises(ValueError, match="convention"):
        read_recording(write_csv(tmp_path / "ok.csv", [good]), convention="opengl")


def test_head_only_recording(tmp_path):
    columns = ("timestamp",) + COLUMNS[1:8]
    stream = read_recording(write_csv(tmp_path / "head.csv", [frame()[:8], frame(0.1)[:8]], columns))
    assert not stream.visible.any() and len(stream) == 2
    assert torch.isfinite(stream.signals()["left"]).all()


def test_repeated_columns_are_refused(tmp_path):
    # Two head_px columns: json / dict reading would keep the last copy (5.5 m off) without a word.
    expect_error(write_csv(tmp_path / "twice.csv", [frame() + [5.5]], COLUMNS + ("head_px",)),
                 "line 1", 'column "head_px"', "fields 2, 25")
    text = json.dumps({"frames": [dict(zip(COLUMNS, frame()))] * 2})
    (tmp_path / "key.json").write_text(text.replace('"head_px": 0,', '"head_px": 0, "head_px": 5.5,', 2)
                                       .replace('"timestamp": 0.0', '"timestamp": 1', 1))
    expect_error(tmp_path / "key.json", "frame 0", 'key "head_px"')
    (tmp_path / "top.json").write_text('{"convention": "unity", "convention": "openxr", "frames": []}')
    expect_error(tmp_path / "top.json", 'key "convention"')


def test_visible_hand_without_pose_is_hidden_with_one_warning(tmp_path, caplog):
    rows = [frame(t / 30) for t in range(6)]
    for row in rows[1:6]:
        row[9:16] = [None] * 7        # left hand flagged visible, no pose cell filled
    path = write_csv(tmp_path / "unposed.csv", rows)
    with caplog.at_level("WARNING", logger="humotion.sparse"):
        stream = read_recording(path)
    assert stream.visible[:, 0].tolist() == [True, False, False, False, False, False]
    assert torch.isnan(stream.left_positions[1:]).all()
    [record] = caplog.records
    message = record.getMessage()
    assert str(path) in message and "left hand" in message and "line 3, line 4, line 5, ..." in message, message
    assert "(5 in all)" in message


def test_numbers_and_names_in_messages(tmp_path):
    head = dict(zip(COLUMNS[1:8], frame()[1:8]))
    frames = [dict(head, timestamp=1.6333333333), dict(head, timestamp=1.6333333333)]
    (tmp_path / "again.json").write_text(json.dumps({"frames": frames}))
    message = expect_error(tmp_path / "again.json", "frame 1", "timestamp 1.6333333333 is not greater than the one before it")
    assert "np." not in message and "float64" not in message, message
    (tmp_path / "nan.json").write_text(json.dumps({"frames": [dict(head, timestamp=0), dict(head, timestamp=None)]}))
    expect_error(tmp_path / "nan.json", "frame 1", "timestamp nan is not a number")
    (tmp_path / "axes.json").write_text(json.dumps({"convention": "opengl", "frames": frames[:1]}))
    expect_error(tmp_path / "axes.json", 'unknown convention "opengl"', "openxr, unity, humotion")
    (tmp_path / "hands.json").write_text(json.dumps({"hand_frame": ["tpose"], "frames": frames[:1]}))
    expect_error(tmp_path / "hands.json", "unknown hand_frame", "tpose, forward")
