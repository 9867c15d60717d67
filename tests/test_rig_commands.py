"""Every command that needs the canonical body reads a rig as `humotion retarget` does (issue 22
item 1): CMU 01_01 (cgspeed BVH) with 3ds-Max-biped joint names through convert --canonical and
body --motion, against the original names; an override file through convert."""

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from humotion.cli import main
from humotion.io import load_motion
from humotion.io.bvh import write_bvh

from test_canonical import renamed


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result


@pytest.fixture(scope="module")
def takes(mocap, tmp_path_factory):
    """The original 2 s and its 3ds-Max-named copy, as BVH files (60 fps, metres)."""
    folder = tmp_path_factory.mktemp("takes")
    original = load_motion(mocap / "cmu_fairmotion/01_01.bvh", units="cmu")[1:241].resample(60.0)
    write_bvh(original, folder / "original.bvh")
    write_bvh(renamed(original, "3ds Max biped"), folder / "max.bvh")
    return folder / "original.bvh", folder / "max.bvh"


def test_convert_canonical_reads_a_3ds_max_named_rig(takes, tmp_path):
    original, max_named = takes
    for path in takes:
        result = run("convert", path, tmp_path / f"{path.stem}_body.bvh", "--canonical")
        assert result.exit_code == 0, result.output
    a, b = (load_motion(tmp_path / f"{p.stem}_body.bvh") for p in takes)
    assert a.skeleton.names == b.skeleton.names and len(a.skeleton.names) == 22
    assert torch.allclose(a.world_positions(), b.world_positions(), atol=1e-4)


def test_convert_canonical_takes_the_retargeters_override_file(takes, tmp_path):
    """The finder would take Bip01_Head; the override file puts the head on the upper neck."""
    _, max_named = takes
    overrides = tmp_path / "rig.toml"
    overrides.write_text('[joints]\nhead = "Bip01_Neck1"\n')
    result = run("convert", max_named, tmp_path / "body.bvh", "--canonical", "--overrides", overrides)
    assert result.exit_code == 0, result.output
    body, source = load_motion(tmp_path / "body.bvh"), load_motion(max_named)
    head = body.world_positions()[:, body.skeleton.index("head")]
    assert torch.allclose(head, source.world_positions()[:, source.skeleton.index("Bip01_Neck1")], atol=1e-4)
    refused = run("convert", max_named, tmp_path / "x.bvh", "--overrides", overrides)
    assert refused.exit_code != 0 and "--overrides goes with --canonical" in refused.output


def test_body_motion_reads_a_3ds_max_named_rig(takes, tmp_path):
    from humotion.body.model import shipped_weights

    if not shipped_weights("low").exists():
        pytest.skip("no shipped body weights")
    outputs = []
    for path in takes:
        out = tmp_path / f"{path.stem}.glb"
        result = run("body", "-o", out, "--height", 1.7, "--weight", 65, "--motion", path)
        assert result.exit_code == 0, result.output
        outputs.append(load_motion(out))
    a, b = outputs
    assert a.num_frames == b.num_frames == 120
    assert np.allclose(a.world_positions().numpy(), b.world_positions().numpy(), atol=1e-4)
