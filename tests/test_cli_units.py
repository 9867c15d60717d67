"""--units on the command line: names and numbers reach the reader, anything else is one line."""

from click.testing import CliRunner

from humotion.cli import main
from tests.data_root import DATA

BVH = DATA / "mocap" / "cmu_fairmotion" / "01_01.bvh"


def height(*options):
    result = CliRunner().invoke(main, ["info", str(BVH), "--json", *options])
    assert result.exit_code == 0, result.output
    import json
    return json.loads(result.output)["height_m"]


def test_a_number_of_metres_per_unit_scales_the_figure():
    assert abs(height("--units", "0.01") - height("--units", "cm")) < 1e-6
    assert abs(height("--units", "0.02") - 2 * height("--units", "cm")) < 1e-3


def test_an_unknown_unit_is_one_line_naming_the_option():
    for bad in ("furlongs", "-1", "0", "nan", "inf"):
        result = CliRunner().invoke(main, ["info", str(BVH), "--units", bad])
        assert result.exit_code == 2
        assert "--units" in result.output and "Traceback" not in result.output
        assert result.exception is None or isinstance(result.exception, SystemExit)
