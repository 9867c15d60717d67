"""A hand flagged visible but given no pose is read as hidden, and said so once per stream or file."""

import warnings

import pytest
import torch
from click.testing import CliRunner

from humotion.sparse.model import SparseConfig, SparsePoser
from humotion.sparse.recording import COLUMNS
from humotion.sparse.tracker import SparseTracker

HEAD = (torch.eye(3), torch.tensor([0.0, 1.6, 0.0]))


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    poser = SparsePoser(SparseConfig(embed=8, hidden=32, feedforward=64, decoder=64))
    poser.fps = 30.0
    return poser.eval()


def test_tracker_says_once_per_stream(model):
    tracker, hidden = SparseTracker(model, runtime="torch"), SparseTracker(model, runtime="torch")
    with pytest.warns(UserWarning, match=r"frame at 0\.1 s: the right hand is flagged visible but has no pose") as said:
        for k in range(4):
            t = k / 30 + 0.1
            pose = tracker.update(HEAD, None, None, False, True, t)
            assert torch.equal(pose.positions, hidden.update(HEAD, None, None, False, False, t).positions)
    assert len(said) == 1
    tracker.reset()
    with pytest.warns(UserWarning, match="left hand"):
        tracker.update(HEAD, None, None, True, False, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SparseTracker(model, runtime="torch").update(HEAD, None, None, False, False, 0.0)


def test_track_command_reports_the_rows(tmp_path, caplog):
    from humotion.cli import main

    head = ["0", "1.6", "0", "1", "0", "0", "0"]
    rows = [[f"{k / 30:.4f}", *head, "1", *[""] * 7, "0", *[""] * 7] for k in range(4)]
    path = tmp_path / "unposed.csv"
    path.write_text("\n".join(",".join(row) for row in [COLUMNS, *rows]) + "\n")
    with caplog.at_level("WARNING", logger="humotion.sparse"):
        result = CliRunner().invoke(main, ["track", str(path)])
    assert result.exit_code == 0, result.output
    [record] = caplog.records          # without pytest's capture, logging's last-resort handler prints it on stderr
    assert record.levelname == "WARNING"
    assert f"{path}: the left hand is flagged visible but has no pose at line 2, line 3, line 4, ..." in record.getMessage()
