"""A recording's hand flagged visible but given no pose is read as hidden, and said so once per file.

(SparseTracker.update cannot be told this: a HeadsetFrame's hand is tracked exactly when it has a pose.)
"""

from click.testing import CliRunner

from humotion.sparse.recording import COLUMNS


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
