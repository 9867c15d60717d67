"""MotionCollection: indexing, subject ids, caching, bad files, subject splits, windows.

Reads small real sources from ../shared/data/mocap (skipped when absent); the full collection
is only loaded by the slow test (pytest --run-slow).
"""

import shutil
import time
from pathlib import Path

import pytest
import torch

from humotion.data import Clip, MotionCollection, MotionWindows, split_subjects, subject_id
from humotion.data import collection as collection_module
from data_root import MOCAP

needs_data = pytest.mark.skipif(not (MOCAP / "cmu_mocgui_s02").is_dir(), reason=f"no mocap data at {MOCAP}")


# -- subject ids -----------------------------------------------------------------------------

@pytest.mark.parametrize("source, path, subject", [
    ("cmu_iclone_ccskeleton", "001_01.bvh.gz", "cmu-01"),
    ("cmu_cyun9601", "amc/01/01_01.amc.gz", "cmu-01"),
    ("cmu_fairmotion", "01_01.amc", "cmu-01"),
    ("cmu_fairmotion", "01_01.bvh", "cmu-01"),
    ("cmu_sxaxmz", "amc/105/105_01.amc.gz", "cmu-105"),
    ("cmu_sxaxmz", "amc/16/16_02__jump.amc.gz", "cmu-16"),
    ("cmu_salsa_beemsoft", "60_01_scaled.bvh.gz", "cmu-60"),
    ("cmu_visdoom_mocapplayer", "amc/07_01-walk.amc", "cmu-07"),
    ("hdm05_jointlearning", "amc/squat1Reps/HDM_bd_squat1Reps_001_120.amc.gz", "hdm05-bd"),
    ("hdm05_jointlearning", "amc/sneak2StepsLStart/HDM_bk_sneak2StepsLStart_006_120.AMC.gz", "hdm05-bk"),
    ("cmu_expmap_li2018", "data/train/walking/walking_1.txt.gz", "cmu-expmap-unknown"),
    ("my_studio", "take_01.bvh", "my_studio-unknown"),
])
def test_subject_ids_name_the_person_across_sources(source, path, subject):
    assert subject_id(source, path) == subject


# -- splits ----------------------------------------------------------------------------------

MINUTES = {f"s{i:02d}": 0.5 + (i * 7919 % 13) / 3 for i in range(40)}


def test_split_is_deterministic_disjoint_and_complete():
    a = split_subjects(MINUTES, (0.8, 0.1, 0.1), seed=0)
    assert a == split_subjects(dict(reversed(MINUTES.items())), (0.8, 0.1, 0.1), seed=0)
    seen = [s for subjects in a.values() for s in subjects]
    assert sorted(seen) == sorted(MINUTES) and len(seen) == len(set(seen))
    assert a != split_subjects(MINUTES, (0.8, 0.1, 0.1), seed=1)


def test_split_balances_minutes():
    total = sum(MINUTES.values())
    for seed in range(5):
        splits = split_subjects(MINUTES, (0.8, 0.1, 0.1), seed=seed)
        shares = [sum(MINUTES[s] for s in splits[n]) / total for n in ("train", "val", "test")]
        assert shares == pytest.approx([0.8, 0.1, 0.1], abs=0.05)


def test_split_pins_and_keeps_groups_together():
    splits = split_subjects(MINUTES, seed=3, pin={"s01": "test", "s02": "train"}, together=[("s05", "s06", "zz")])
    assert "s01" in splits["test"] and "s02" in splits["train"]
    assert [("s05" in v) == ("s06" in v) for v in splits.values()] == [True] * 3
    with pytest.raises(ValueError, match="unknown split"):
        split_subjects(MINUTES, pin={"s01": "holdout"})
    with pytest.raises(ValueError, match="share a split"):
        split_subjects(MINUTES, pin={"s05": "val", "s06": "test"}, together=[("s05", "s06")])


def test_default_groups_keep_coupled_subjects_together():
    minutes = {**MINUTES, "cmu-60": 3.8, "cmu-61": 3.8, "cmu-expmap-unknown": 9.4, "cmu-16": 2.3, "cmu-02": 3.6}
    for seed in range(6):
        splits = split_subjects(minutes, seed=seed)
        home = {s: name for name, subjects in splits.items() for s in subjects}
        assert home["cmu-60"] == home["cmu-61"]
        assert home["cmu-expmap-unknown"] == home["cmu-16"] == home["cmu-02"]


def test_evaluation_only_sources_go_to_test():
    def clip(source, subject, minutes):
        return Clip(Path(f"/x/{source}/{subject}.amc"), source, subject, int(minutes * 7200), 120.0, 31, "31j")

    clips = [clip("cmu_a", f"cmu-{i:02d}", 1 + i % 4) for i in range(20)]
    clips += [clip("hdm05_jointlearning", f"hdm05-{a}", 2) for a in ("bd", "bk", "dg")]
    collection = MotionCollection(clips)
    for seed in range(4):
        splits = collection.split(seed=seed)
        assert {"hdm05-bd", "hdm05-bk", "hdm05-dg"} <= set(splits["test"])
        cmu_total = sum(1 + i % 4 for i in range(20))
        train = sum(c.duration for c in clips if c.subject in splits["train"]) / 60
        assert train == pytest.approx(0.8 * cmu_total, rel=0.1)
    assert "hdm05-bd" in collection.split(pin={"hdm05-bd": "val"})["val"]
    assert "hdm05-bd" in collection.split(evaluation_only=())["train"] + collection.split(evaluation_only=())["val"] + \
        collection.split(evaluation_only=())["test"]


# -- loading real files ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def small(cache_dir):
    """Two small sources: CMU 02 (ASF/AMC) and fairmotion (01_01 as AMC and BVH, 11_01)."""
    return MotionCollection.load(MOCAP, sources=["cmu_mocgui_s02", "cmu_fairmotion"], cache_dir=cache_dir, progress=False)


@needs_data
def test_load_indexes_small_sources(small):
    assert small.sources() == ["cmu_fairmotion", "cmu_mocgui_s02"]
    assert small.skipped == []
    assert len(small) == 13
    assert small.subjects() == ["cmu-01", "cmu-02", "cmu-11"]
    by_name = {(c.source, c.path.name): c for c in small}
    s11 = by_name["cmu_fairmotion", "11_01.amc"]
    assert (s11.frames, s11.fps, s11.num_joints) == (597, 120.0, 31)
    assert sum(c.frames for c in small if c.source == "cmu_mocgui_s02") == 12815  # SOURCE.md
    assert by_name["cmu_fairmotion", "01_01.bvh"].subject == by_name["cmu_fairmotion", "01_01.amc"].subject
    motion = s11.load()
    assert motion.num_frames == 597 and motion.skeleton.num_joints == 31
    table = small.summary()
    assert "cmu_mocgui_s02" in table and "1.78" in table and "total" in table


@needs_data
def test_second_load_reads_only_the_cache(small, cache_dir, monkeypatch):
    def no_parsing(*args, **kwargs):
        raise AssertionError("second load parsed a file instead of reading the cache")

    monkeypatch.setattr(collection_module, "load_motion", no_parsing)
    start = time.perf_counter()
    again = MotionCollection.load(MOCAP, sources=["cmu_mocgui_s02", "cmu_fairmotion"], cache_dir=cache_dir, progress=False)
    motions = [clip.load() for clip in again]
    assert time.perf_counter() - start < 10
    assert [(c.path, c.subject, c.frames, c.signature) for c in again] == [(c.path, c.subject, c.frames, c.signature) for c in small]
    first = small.clips[0].load()
    assert torch.equal(motions[0].rotations, first.rotations) and motions[0].skeleton.names == first.skeleton.names
    # a folder holding a SOURCE.md is one source; the cache is keyed by file, not by root
    alone = MotionCollection.load(MOCAP / "cmu_fairmotion", cache_dir=cache_dir, progress=False)
    assert alone.sources() == ["cmu_fairmotion"] and len(alone) == 3


@needs_data
def test_without_cache_motions_stay_in_memory(tmp_path, monkeypatch):
    monkeypatch.setenv("HUMOTION_CACHE", str(tmp_path / "env-cache"))
    collection = MotionCollection.load(MOCAP, sources=["cmu_fairmotion"], cache=False, workers=1, progress=False)
    assert len(collection) == 3 and not (tmp_path / "env-cache").exists()
    assert collection.clips[0].load() is collection.clips[0].load()


@needs_data
def test_corrupt_cache_entries_are_rebuilt(tmp_path):
    source = tmp_path / "data" / "cmu_fairmotion"
    source.mkdir(parents=True)
    for name in ("11.asf", "11_01.amc"):
        shutil.copy(MOCAP / "cmu_fairmotion" / name, source / name)
    cache = tmp_path / "cache"
    first = MotionCollection.load(tmp_path / "data", cache_dir=cache, progress=False)
    entries = list((cache / "motions").glob("*.npz"))
    assert len(entries) == 1
    entries[0].write_bytes(entries[0].read_bytes()[:500])  # truncated zip
    second = MotionCollection.load(tmp_path / "data", cache_dir=cache, progress=False)
    assert second.clips[0].frames == first.clips[0].frames == 597
    entries[0].write_bytes(b"not a zip file")
    assert torch.equal(second.clips[0].load().rotations, first.clips[0].load().rotations)


@needs_data
def test_cache_entry_replaced_by_a_folder_leaves_no_temporary_files(tmp_path):
    source = tmp_path / "data" / "cmu_fairmotion"
    source.mkdir(parents=True)
    for name in ("11.asf", "11_01.amc"):
        shutil.copy(MOCAP / "cmu_fairmotion" / name, source / name)
    cache = tmp_path / "cache"
    first = MotionCollection.load(tmp_path / "data", cache_dir=cache, progress=False)
    [entry] = (cache / "motions").iterdir()
    entry.unlink()
    entry.mkdir()                   # something else now stands at the entry's name
    for _ in range(2):
        again = MotionCollection.load(tmp_path / "data", cache_dir=cache, workers=1, progress=False)
        assert torch.equal(again.clips[0].load().rotations, first.clips[0].load().rotations)
    assert [p.name for p in (cache / "motions").iterdir()] == [entry.name]


@needs_data
def test_data_reached_through_symlinks(tmp_path):
    """A root that is a link, holding a source that is a link to another drive: both are read,
    and every path is the resolved root joined with the file's path under it."""
    tree = tmp_path / "tree"
    tree.mkdir()
    (tree / "cmu_fairmotion").symlink_to(MOCAP / "cmu_fairmotion", target_is_directory=True)
    (tree / "loop").symlink_to(tree, target_is_directory=True)             # a link back up the tree ends
    (tmp_path / "link").symlink_to(tree, target_is_directory=True)
    collection = MotionCollection.load(tmp_path / "link", cache_dir=tmp_path / "cache", progress=False)
    assert collection.root == tree.resolve()
    assert [str(c.path.relative_to(collection.root)) for c in collection] == [
        "cmu_fairmotion/01_01.amc", "cmu_fairmotion/01_01.bvh", "cmu_fairmotion/11_01.amc"]
    assert collection.subjects() == ["cmu-01", "cmu-11"] and collection.skipped == []
    assert collection.clips[2].load().num_frames == 597


@needs_data
def test_bad_files_are_reported_by_name_and_skipped(tmp_path):
    source = tmp_path / "mocap" / "my_copy"
    source.mkdir(parents=True)
    shutil.copy(MOCAP / "cmu_mocgui_s02" / "02.asf", source / "02.asf")
    shutil.copy(MOCAP / "cmu_mocgui_s02" / "02_04.amc", source / "02_04.amc")
    text = (MOCAP / "cmu_mocgui_s02" / "02_04.amc").read_text()
    cut = text.index("\nlfemur ", len(text) // 2) + len("\nlfemur ")
    cut += text[cut:].index(" ")  # stop after the first of lfemur's three values
    (source / "02_05.amc").write_text(text[:cut])
    (source / "garbage.bvh").write_bytes(b"HIERARCHY\nROOT Hips\n{ this is not a bvh file \x01\x02")
    (source / "take.fbx").write_bytes(b"Kaydara FBX Binary  \x00")
    collection = MotionCollection.load(tmp_path / "mocap", cache_dir=tmp_path / "cache", progress=False)
    assert [c.path.name for c in collection] == ["02_04.amc"]
    reasons = {s.path.name: s.reason for s in collection.skipped}
    assert set(reasons) == {"02_05.amc", "garbage.bvh", "take.fbx"}
    assert reasons["take.fbx"] == "unsupported format"
    assert "02_05.amc" in reasons["02_05.amc"] and "garbage.bvh" in reasons["garbage.bvh"]
    table = collection.summary()
    assert "02_05.amc" in table and "garbage.bvh" in table and "unsupported format" in table


# -- windows ---------------------------------------------------------------------------------

@needs_data
def test_windows_refuse_mixed_skeletons(small):
    assert len(small.signatures()) == 2  # CMU ASF (31) and the cgspeed BVH of 01_01
    with pytest.raises(ValueError, match="mix skeletons"):
        small.windows(length=40, fps=30.0)


@needs_data
def test_windows_cut_resampled_clips(small):
    amc = next(s for s, n in small.signatures().items() if n == 12)
    windows = small.windows(length=40, fps=30.0, signature=amc, stride=20)
    assert isinstance(windows, MotionWindows)
    expected = 0
    for clip in small.filter(signature=amc):
        frames = clip.load().resample(30.0).num_frames
        expected += max(0, (frames - 40) // 20 + 1)
    assert len(windows) == expected
    item = windows[5]
    assert item["rotations"].shape == (40, 31, 4) and item["root_positions"].shape == (40, 3)
    assert item["offsets"].shape == (31, 3)
    clip, start = int(item["clip"]), int(item["start"])
    assert torch.equal(item["root_positions"], windows.motions[clip].root_positions[start:start + 40])
    batch = next(iter(torch.utils.data.DataLoader(windows, batch_size=8, shuffle=True)))
    assert batch["rotations"].shape == (8, 40, 31, 4)


@needs_data
def test_windows_by_split_use_only_that_splits_subjects(small):
    amc = small.filter(sources=["cmu_mocgui_s02"])
    splits = small.split(seed=0, pin={"cmu-02": "val"})
    assert "cmu-02" in splits["val"]
    val = amc.windows(length=30, fps=30.0, split="val", splits=splits)
    train = amc.windows(length=30, fps=30.0, split="train", splits=splits)
    assert len(val) > 0 and len(train) == 0
    assert small.split(seed=0) == small.split(seed=0)


@needs_data
def test_windows_transform_and_augment(small):
    from humotion.data import RandomAugment, change_speed

    amc = small.filter(sources=["cmu_mocgui_s02"]).clips[:2]
    windows = MotionWindows(amc, 32, 30.0, transform=lambda m: change_speed(m, 2.0),
                            augment=RandomAugment(seed=0), as_motion=True)
    plain = MotionWindows(amc, 32, 30.0)
    assert len(windows) < len(plain)
    assert windows[0].num_frames == 32 and windows[0].fps == 30.0


# -- the whole collection (slow) -------------------------------------------------------------

@pytest.mark.slow
@needs_data
def test_full_collection_loads_caches_and_splits():
    """Minutes on a first run (fills the default cache), seconds afterwards; pytest --run-slow."""
    collection = MotionCollection.load(MOCAP, progress=False)  # fills the default cache
    assert collection.minutes > 60 and len(collection.subjects()) >= 19
    assert {s.path.suffix for s in collection.skipped if s.reason == "unsupported format"} == {".fbx"}
    start = time.perf_counter()
    again = MotionCollection.load(MOCAP, progress=False)
    frames = sum(clip.load().num_frames for clip in again)
    assert time.perf_counter() - start < 30
    assert frames == sum(c.frames for c in collection)
    splits = again.split()
    home = {s: name for name, subjects in splits.items() for s in subjects}
    assert len(home) == sum(len(v) for v in splits.values()) == len(again.subjects())
    assert {home[s] for s in again.subjects("hdm05_jointlearning")} == {"test"}
    assert home["cmu-60"] == home["cmu-61"] and home["cmu-expmap-unknown"] == home["cmu-16"]
    assert splits == again.split()
