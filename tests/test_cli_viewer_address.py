"""The viewer's address is printed once (the viewer prints it when it starts serving)."""

import threading

from click.testing import CliRunner

from humotion.cli import main
from tests.data_root import DATA


def test_view_prints_the_address_once():
    import humotion.viewer as viewer_module

    started = threading.Event()
    original_run = viewer_module.MotionViewer.run

    def run_then_stop(self):
        threading.Timer(0.2, self.stop).start()
        started.set()
        original_run(self)

    viewer_module.MotionViewer.run = run_then_stop
    try:
        result = CliRunner().invoke(main, ["view", str(DATA / "mocap" / "cmu_fairmotion" / "01_01.bvh"),
                                           "--port", "0", "--no-open"])
    finally:
        viewer_module.MotionViewer.run = original_run
    assert result.exit_code == 0, result.output
    assert started.is_set()
    assert result.output.count("http://127.0.0.1:") == 1, result.output
