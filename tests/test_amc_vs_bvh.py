"""The proof of the ASF/AMC rotation conventions: CMU take 01_01 read twice, independently.

cmu_fairmotion holds the same take as the original ASF/AMC (01.asf + 01_01.amc) and as CMU's
cgspeed BVH conversion (01_01.bvh: frame 0 an added T-pose, so BVH frame i+1 is AMC frame i;
lengths in CMU units, 1/0.45 inch). The two readers share nothing but Motion's forward
kinematics, so joint positions that agree on every frame pin down the AMC composition
(M = Rz @ Ry @ Rx for "rx ry rz", conjugated by the bone axis C): the alternative, intrinsic
"XYZ" (M = Rx @ Ry @ Rz), misplaces the feet by more than a metre on some frames of this take.

Joints are matched by where they are: an ASF joint sits at the START of its bone, so lfemur is
the hip (BVH LeftUpLeg), ltibia the knee (LeftLeg), lfoot the ankle (LeftFoot), ltoes the ball
of the foot (LeftToeBase); lowerback starts at the root (BVH LowerBack, offset 0 from Hips),
upperback at the end of lowerback (Spine), thorax at the end of upperback (Spine1).
The BVH has no thorax segment: its Neck and shoulders hang off Spine1 with zero offset, so
the whole upper body sits one thorax bone (2.06488 units = 11.66 cm) lower than in the ASF,
and it also drops the wrist bone (its fingers start at the end of the forearm).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FAIR = DATA / "mocap" / "cmu_fairmotion"
CMU_UNIT = 0.0254 / 0.45

LOWER_BODY = {  # BVH joint -> ASF joint at the same place
    "Hips": "root",
    "LeftUpLeg": "lfemur", "LeftLeg": "ltibia", "LeftFoot": "lfoot", "LeftToeBase": "ltoes",
    "RightUpLeg": "rfemur", "RightLeg": "rtibia", "RightFoot": "rfoot", "RightToeBase": "rtoes",
    "LowerBack": "lowerback", "Spine": "upperback", "Spine1": "thorax",
}
UPPER_BODY = {  # BVH joint -> ASF joint it stands for, one thorax bone apart
    "Neck": "lowerneck", "Neck1": "upperneck", "Head": "head",
    "LeftShoulder": "lclavicle", "LeftArm": "lhumerus", "LeftForeArm": "lradius", "LeftHand": "lwrist",
    "RightShoulder": "rclavicle", "RightArm": "rhumerus", "RightForeArm": "rradius", "RightHand": "rwrist",
}


@pytest.fixture(scope="module")
def both():
    for name in ("01.asf", "01_01.amc", "01_01.bvh"):
        if not (FAIR / name).exists():
            pytest.skip(f"data file not found: {FAIR / name}")
    bvh_module = pytest.importorskip("humotion.io.bvh")
    from humotion.io.asf_amc import read_amc, read_asf

    asf = read_asf(FAIR / "01.asf")
    amc = read_amc(FAIR / "01_01.amc", asf=asf)
    bvh = bvh_module.read_bvh(FAIR / "01_01.bvh", units="cmu")
    return asf, amc, bvh


def positions(both):
    asf, amc, bvh = both
    assert bvh.num_frames == 2752 and amc.num_frames == 2751
    return amc.world_positions().numpy(), bvh.world_positions()[1:].numpy()  # BVH frame 0 is the T-pose


def distances(both, pairs, shift=None):
    asf, amc, bvh = both
    a, b = positions(both)
    out = {}
    for bvh_name, asf_name in pairs.items():
        p = b[:, bvh.skeleton.index(bvh_name)] + (0 if shift is None else shift)
        out[(bvh_name, asf_name)] = np.linalg.norm(p - a[:, asf.skeleton.index(asf_name)], axis=-1)
    return out


def test_lower_body_agrees_on_every_frame(both):
    errors = distances(both, LOWER_BODY)
    worst = max(e.max() for e in errors.values())
    print(f"\nAMC vs BVH, legs, hips and lower spine: max error {worst * 1000:.4f} mm over "
          f"{len(next(iter(errors.values())))} frames x {len(errors)} joints")
    for pair, e in errors.items():
        assert e.max() < 0.01, f"{pair}: {e.max() * 100:.2f} cm at frame {int(e.argmax())}"
    assert worst < 0.001  # in fact sub-millimetre: same numbers, same maths


def test_intrinsic_composition_would_fail(both, monkeypatch):
    """The check discriminates: reading the AMC with intrinsic "XYZ" (Rx @ Ry @ Rz) instead puts
    the feet far from the BVH's."""
    from types import SimpleNamespace

    from humotion import rotations
    from humotion.io import amc as amc_module
    from humotion.io import asf as asf_module
    from humotion.io import asf_amc

    asf, amc, bvh = both
    wrong = SimpleNamespace(**{n: getattr(rotations, n) for n in dir(rotations) if not n.startswith("__")})
    wrong.euler_to_quat = lambda convention, angles, degrees=True: rotations.euler_to_quat(convention.upper(), angles, degrees)
    monkeypatch.setattr(asf_module, "rot", wrong)  # the axis rotations C
    monkeypatch.setattr(amc_module, "rot", wrong)  # the motion rotations M
    other = asf_amc.read_amc(FAIR / "01_01.amc", asf=asf_amc.read_asf(FAIR / "01.asf"))
    a = other.world_positions().numpy()
    b = bvh.world_positions()[1:].numpy()
    e = np.linalg.norm(a[:, asf.skeleton.index("lfoot")] - b[:, bvh.skeleton.index("LeftFoot")], axis=-1)
    print(f"\nintrinsic XYZ instead: left ankle off by up to {e.max() * 100:.0f} cm")
    assert e.max() > 0.5


def test_the_feet_move(both):
    """Guard against a vacuous match: the take really moves the compared joints (jumps, turns)."""
    asf, amc, _ = both
    a, _ = positions(both)
    for name in ("root", "lfoot", "rtoes"):
        track = a[:, asf.skeleton.index(name)]
        assert np.ptp(track, axis=0).max() > 1.0  # metres travelled along some axis


def test_upper_body_is_one_thorax_bone_off(both):
    asf, amc, bvh = both
    a, b = positions(both)
    thorax = asf.lengths["thorax"]
    assert thorax == pytest.approx(2.06488 * CMU_UNIT) and thorax == pytest.approx(0.1166, abs=5e-4)
    # BVH Neck sits at the ASF thorax START (the upper back's end), not at lowerneck
    neck = b[:, bvh.skeleton.index("Neck")]
    assert np.linalg.norm(neck - a[:, asf.skeleton.index("thorax")], axis=-1).max() < 0.01
    gap = np.linalg.norm(neck - a[:, asf.skeleton.index("lowerneck")], axis=-1)
    print(f"\nBVH Neck to ASF lowerneck: {gap.min() * 100:.2f}-{gap.max() * 100:.2f} cm (thorax bone {thorax * 100:.2f} cm)")
    np.testing.assert_allclose(gap, thorax, atol=0.002)
    # Every upper-body joint differs by about that much, and by exactly the thorax bone vector:
    raw = distances(both, UPPER_BODY)
    for pair, e in raw.items():
        assert 0.10 < e.min() and e.max() < 0.13, pair
    shift = a[:, asf.skeleton.index("lowerneck")] - a[:, asf.skeleton.index("thorax")]
    shifted = distances(both, UPPER_BODY, shift)
    worst = max(e.max() for e in shifted.values())
    print(f"upper body after adding the thorax bone to the BVH: max error {worst * 1000:.4f} mm")
    assert worst < 0.01


def test_hands_also_lack_the_wrist_bone(both):
    asf, amc, bvh = both
    a, b = positions(both)
    shift = a[:, asf.skeleton.index("lowerneck")] - a[:, asf.skeleton.index("thorax")]
    hand = b[:, bvh.skeleton.index("LeftFingerBase")] + shift
    gap = np.linalg.norm(hand - a[:, asf.skeleton.index("lhand")], axis=-1)
    np.testing.assert_allclose(gap, asf.lengths["lwrist"], atol=0.002)  # 1.74178 units = 9.8 cm


def test_end_sites_agree(both):
    asf, amc, bvh = both
    a = amc.end_site_positions().numpy()
    b = bvh.end_site_positions()[1:].numpy()
    for bvh_name, asf_name in (("LeftToeBase_end", "ltoes_end"), ("RightToeBase_end", "rtoes_end")):
        e = np.linalg.norm(b[:, bvh.skeleton.end_site_names.index(bvh_name)]
                           - a[:, asf.skeleton.end_site_names.index(asf_name)], axis=-1)
        assert e.max() < 0.01, (bvh_name, e.max())
