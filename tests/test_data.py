import numpy as np
import pytest
import torch
from helpers import write_humanml3d_fixture

from party.data import (FeatureBank, MotionStore, Normalizer, TextMotionDataset, WindowDataset,
                        collate_text_motion)
from party.data.humanml3d import DatasetError, parse_caption_line, scan_dataset
from party.data.index import Index

TIMED = ("a man walks then jumps.#a/DET man/NOUN walk/VERB then/ADV jump/VERB#0.0#0.0\n"
         "the man walks forward.#the/DET man/NOUN walk/VERB forward/ADV#0.0#2.5\n"
         "he walks ahead.#he/PRON walk/VERB ahead/ADV#0.0#2.5\n"
         "the man jumps.#the/DET man/NOUN jump/VERB#nan#nan\n")


@pytest.fixture()
def fixture_root(tmp_path):
    return write_humanml3d_fixture(
        tmp_path / "HumanML3D", {"train": ["000001", "M000001", "000002", "M000002"],
                                 "val": ["000003"], "test": ["000004", "M000004"]},
        n_frames=80, texts={"000001": TIMED})


def scan(root, **kw):
    args = dict(feat_dim=263, fps=20, min_len=40, max_len=199, progress=False)
    return scan_dataset(root, **(args | kw))


def test_reads_real_layout_with_timed_captions_and_mirrors(fixture_root):
    rep = scan(fixture_root)
    assert not rep.rejected and not rep.bad_lines
    ids = {c["id"]: c for c in rep.clips}
    assert "M000001" in ids and ids["M000001"]["split"] == "train"
    whole = ids["000001"]
    # the nan#nan line counts as a whole-clip caption, like HumanML3D's loader
    assert [c["caption"] for c in whole["captions"]] == ["a man walks then jumps.", "the man jumps."]
    timed = ids["000001#0-50"]
    assert (timed["start"], timed["end"]) == (0, 50) and len(timed["captions"]) == 2
    assert timed["captions"][0]["tokens"] == ["the/DET", "man/NOUN", "walk/VERB", "forward/ADV"]


def test_caption_line_errors_name_file_and_line():
    with pytest.raises(DatasetError, match=r"x\.txt:3: expected"):
        parse_caption_line("no hashes here", "x.txt", 3)
    with pytest.raises(DatasetError, match="empty caption"):
        parse_caption_line("#a/DET#0#0", "x.txt", 1)
    with pytest.raises(DatasetError, match="word/POS"):
        parse_caption_line("a man#a man#0#0", "x.txt", 1)
    with pytest.raises(DatasetError, match="not numbers"):
        parse_caption_line("a man#a/DET man/NOUN#zero#0", "x.txt", 1)


def test_bad_files_are_skipped_with_reason(fixture_root):
    r = fixture_root
    np.save(r / "new_joint_vecs/000002.npy", np.zeros((80, 250), np.float32))          # wrong width
    bad = np.load(r / "new_joint_vecs/000003.npy")
    bad[5, 7] = np.inf
    np.save(r / "new_joint_vecs/000003.npy", bad)                                       # Inf
    (r / "new_joint_vecs/000004.npy").write_bytes(b"not an npy file")                  # unreadable
    (r / "texts/M000004.txt").write_text("\n# broken line\n")                           # no valid caption
    np.save(r / "new_joint_vecs/M000002.npy", np.zeros((10, 263), np.float32))         # too short
    (r / "test.txt").write_text("000004\nM000004\n999999\n")                             # absent file
    rep = scan(r)
    reasons = {x["name"]: x for x in rep.rejected}
    assert "(T, 263)" in reasons["000002"]["reason"] and "000002.npy" in reasons["000002"]["reason"]
    assert "NaN or Inf" in reasons["000003"]["reason"]
    assert "not a valid .npy file" in reasons["000004"]["reason"]
    assert "no valid caption" in reasons["M000004"]["reason"]
    assert "length 10" in reasons["M000002"]["reason"]
    assert "999999.npy: file missing" in reasons["999999"]["reason"]
    assert len(rep.bad_lines) == 1 and rep.bad_lines[0]["line"] == 2
    assert {c["id"] for c in rep.clips} == {"000001", "000001#0-50", "M000001"}
    with pytest.raises(DatasetError, match="strict"):
        scan(r, strict=True)


GOOD = "a man walks.#a/DET man/NOUN walk/VERB#0.0#0.0\n"


@pytest.mark.parametrize("case", ["bad_line", "short_timed", "timed_after_end", "two_splits"])
def test_strict_stops_on_every_kind_of_problem(fixture_root, case):
    """Each of these alone is skipped and counted by default, and stops a strict scan,
    naming the file (and line)."""
    r = fixture_root
    where = {"bad_line": ("texts/000002.txt", GOOD + "broken line without fields\n", "000002.txt:2"),
             "short_timed": ("texts/000002.txt", GOOD + "he walks.#he/PRON walk/VERB#0.0#1.0\n",
                             "000002.txt:2"),
             "timed_after_end": ("texts/000002.txt", GOOD + "he walks.#he/PRON walk/VERB#9.0#11.0\n",
                                 "000002.txt:2"),
             "two_splits": ("val.txt", "000003\n000002\n", "val.txt")}[case]
    (r / where[0]).write_text(where[1])
    rep = scan(r)
    assert len(rep.rejected) + len(rep.bad_lines) == 1
    with pytest.raises(DatasetError, match=rf"{where[2]}.*strict"):
        scan(r, strict=True)


def test_new_joints_checked_against_features(fixture_root):
    r = fixture_root
    ok = np.load(r / "new_joints/000002.npy")
    np.save(r / "new_joints/000002.npy", ok + 0.05)                                    # another motion
    np.save(r / "new_joints/000003.npy", ok[:, :10])                                    # wrong shape
    bad = np.load(r / "new_joints/000004.npy")
    bad[3, 2, 1] = np.nan
    np.save(r / "new_joints/000004.npy", bad)                                          # NaN
    (r / "new_joints/M000004.npy").unlink()                                             # absent: fine
    rep = scan(r, n_joints=22, joints_tol=0.01)
    reasons = {x["name"]: x["reason"] for x in rep.rejected}
    assert set(reasons) == {"000002", "000003", "000004"}
    assert "new_joints/000002.npy: differs from recover_from_ric" in reasons["000002"]
    assert "(80, 22, 3)" in reasons["000003"] and "NaN or Inf" in reasons["000004"]
    assert all("new_joints" in x["file"] for x in rep.rejected)
    assert not scan(fixture_root.parent / "HumanML3D", n_joints=None).rejected   # check off


def test_clamped_timed_caption_and_empty_split_are_reported(fixture_root):
    r = fixture_root
    (r / "texts/000002.txt").write_text(GOOD + "he walks.#he/PRON walk/VERB#2.0#9.0\n")
    (r / "val.txt").write_text("")
    rep = scan(r)
    assert [(c["line"], "cut at 80" in c["reason"]) for c in rep.clamped] == [(2, True)]
    assert "000002#40-80" in {c["id"] for c in rep.clips}
    assert any("val split is empty" in w for w in rep.warnings)


def _index(root, clips):
    return Index("fixture", str(root), 20, 263, 22, "t2m", clips)


def test_datasets_and_normalizer(fixture_root):
    clips = scan(fixture_root).clips
    index = _index(fixture_root, clips)
    norm = Normalizer.load(fixture_root)
    store = MotionStore(fixture_root, 263)
    raw = store.features("000001")
    assert np.allclose(norm.denorm(norm.norm(raw)), raw, atol=1e-5)
    bank = FeatureBank(index, "train", norm, store)
    assert bank.data.dtype == torch.float32 and len(bank) == 5
    k = [c["id"] for c in bank.clips].index("000001#0-50")
    assert torch.allclose(bank.get(k), torch.tensor(norm.norm(raw[:50])))
    win = WindowDataset(index, store, "train", 64, norm)
    assert len(win) == 4 and win[0].shape == (64, 263)           # the 50-frame clip is too short
    tm = TextMotionDataset(index, store, "train", norm, max_len=196, unit_len=4, captions="all")
    assert len(tm) == sum(len(c["captions"]) for c in index.clips("train"))
    batch = collate_text_motion([tm[i] for i in range(len(tm))])
    assert batch["motion"].shape[0] == len(tm) and batch["length"].max() == 80
    assert all(length % 4 == 0 for length in batch["length"].tolist())
