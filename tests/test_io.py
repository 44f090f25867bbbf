"""Reading stage outputs (``party.io.read_json``) and the SQLite cache setup (``party.sqlite``)
shared by the index, the part-text and embedding caches and stores."""
from __future__ import annotations

import json
import os
import sqlite3

import numpy as np
import pytest

from party.data.index import load_index
from party.io import load_npy, read_json, require
from party.sqlite import SQLiteCache, connect, select_in
from party.text.cache import PartTextCache, load_part_texts
from party.text.store import EmbeddingCache, EmbeddingStore
from party.tokenizers.tokens import TokenStore, write_token_store


def test_read_json_says_what_to_rerun(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"a\.json: thing not found; run `party make_a`"):
        read_json(tmp_path / "a.json", "party make_a", what="thing")
    (tmp_path / "a.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"a\.json: not valid JSON .*; rerun `party make_a`"):
        read_json(tmp_path / "a.json", "party make_a")
    (tmp_path / "a.json").write_text('{"x": [1, 2]}')
    assert read_json(tmp_path / "a.json", "party make_a") == {"x": [1, 2]}
    assert require(tmp_path / "a.json", "party make_a") == tmp_path / "a.json"


def test_stage_outputs_name_the_stage_to_rerun(tmp_path):
    with pytest.raises(FileNotFoundError, match="prepared index not found; run `party prepare`"):
        load_index(tmp_path)
    (tmp_path / "index.json").write_text("[")
    with pytest.raises(ValueError, match="rerun `party prepare`"):
        load_index(tmp_path)
    with pytest.raises(FileNotFoundError, match="run `party cache_part_texts`"):
        load_part_texts(tmp_path)
    with pytest.raises(FileNotFoundError, match="current.json.*run `party embed_texts`"):
        EmbeddingStore.open(tmp_path)
    enc = tmp_path / "enc"
    EmbeddingStore.write(enc, ["a", "b"], np.ones((2, 3)), {"encoder_id": "enc"})
    (enc / "keys.json").write_text("{")
    with pytest.raises(ValueError, match=r"keys\.json: not valid JSON .*rerun `party embed_texts`"):
        EmbeddingStore.open(tmp_path)
    (enc / "embeddings.npy").unlink()
    (enc / "keys.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match=r"embeddings\.npy: not found; run `party embed_texts`"):
        EmbeddingStore.open(enc)


def test_a_damaged_npy_output_names_the_file_and_the_stage(tmp_path):
    """A truncated or foreign .npy (a disk filled mid-copy, a file from elsewhere) is a ValueError
    naming the file and the stage to rerun, not numpy's bare "EOF: reading array header"."""
    with pytest.raises(FileNotFoundError, match=r"x\.npy: not found; run `party make_x`"):
        load_npy(tmp_path / "x.npy", "party make_x")
    np.save(tmp_path / "x.npy", np.arange(6).reshape(2, 3))
    assert load_npy(tmp_path / "x.npy", "party make_x", mmap=True).shape == (2, 3)
    data = (tmp_path / "x.npy").read_bytes()
    for bad in (data[:60], b"not an array", b""):
        (tmp_path / "x.npy").write_bytes(bad)
        with pytest.raises(ValueError, match=r"x\.npy: not a readable \.npy file .*rerun `party make_x`"):
            load_npy(tmp_path / "x.npy", "party make_x")
    write_token_store(tmp_path / "tok", [({"motion": "m"}, np.arange(4))], {"m": 0},
                      {"stream": "holistic", "window": 4, "tail": "crop", "codebook_size": 16})
    codes = tmp_path / "tok" / "codes.npy"
    codes.write_bytes(codes.read_bytes()[:100])
    with pytest.raises(ValueError, match=r"tok/codes\.npy: not a readable .*rerun `party extract_tokens`"):
        TokenStore.open(tmp_path / "tok")
    enc = tmp_path / "emb" / "enc"
    EmbeddingStore.write(enc, ["a", "b"], np.ones((2, 3)), {"encoder_id": "enc"})
    (enc / "embeddings.npy").write_bytes((enc / "embeddings.npy").read_bytes()[:50])
    with pytest.raises(ValueError, match=r"embeddings\.npy: not a readable .*rerun `party embed_texts`"):
        EmbeddingStore.open(enc)


def test_a_damaged_model_file_names_the_file_and_the_stage(tmp_path):
    """A truncated generator, tokenizer or evaluator file is a ValueError naming the file and the
    stage to rerun, not torch's bare "OSError: [Errno 22] Invalid argument"."""
    import torch

    from party.evaluation.checkpoint import torch_load
    from party.methods.party import PartyFamily
    load_generator = PartyFamily.load
    from party.io import load_torch
    from party.tokenizers import load_tokenizer

    torch.save({"w": torch.ones(1000)}, tmp_path / "good.pt")
    assert torch.equal(load_torch(tmp_path / "good.pt", "party make_x", "thing")["w"], torch.ones(1000))
    (tmp_path / "model.pt").write_bytes((tmp_path / "good.pt").read_bytes()[:300])
    for load, stage in ((load_generator, "party train_generator"), (load_tokenizer, "party train_vqvae"),
                        (torch_load, "party train_evaluator")):
        with pytest.raises(ValueError, match=rf"model\.pt: cannot read .*; rerun `{stage}`"):
            load(tmp_path / "model.pt")
    with pytest.raises(FileNotFoundError, match=r"nothing\.pt: generator not found; run `party train_generator`"):
        load_generator(tmp_path / "nothing.pt")


def test_part_texts_are_checked_for_the_configured_parts(tmp_path):
    path = tmp_path / "part_texts.json"
    path.write_text(json.dumps({"c1": {"arms": "a", "legs": "b"}, "c2": {"arms": "c", "legs": "d"}}))
    assert load_part_texts(path)["c2"] == {"arms": "c", "legs": "d"}
    assert load_part_texts(tmp_path, ["legs"])["c1"]["legs"] == "b"
    with pytest.raises(ValueError, match="'arms'/'torso'"):
        load_part_texts(path, ["arms", "torso"])
    path.write_text(json.dumps({"c1": {"arms": "a", "legs": "b"}, "c2": {"arms": "c", "legs": ""}}))
    with pytest.raises(ValueError, match="'c2' lacks non-empty 'arms'/'legs' texts"):
        load_part_texts(path)


@pytest.mark.parametrize("cls, message", [(PartTextCache, r"not a usable part-text cache \(.*\); delete it to rebuild \(every caption"),
                                          (EmbeddingCache, r"not a usable embedding cache .*; delete it to rebuild")])
def test_caches_share_one_sqlite_setup(tmp_path, cls, message):
    path = tmp_path / "sub" / "cache.sqlite"
    with cls(path) as cache:                                   # creates the folder and the schema
        assert cache.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert cache.db.execute("PRAGMA synchronous").fetchone()[0] == 1          # NORMAL
        assert cache.count() == 0
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not a database" * 100)
    with pytest.raises(sqlite3.DatabaseError, match=message):
        cls(bad)


def test_damage_inside_a_cache_names_the_file_and_the_way_out(tmp_path):
    """Corruption that opening does not see (a page in the middle) surfaces on the first query
    as an error naming the file and how to recover, not a bare 'malformed'."""
    path = tmp_path / "emb.sqlite"
    keys = [f"{i:040d}" for i in range(3000)]
    with EmbeddingCache(path) as cache:
        cache.put_many("enc", keys, np.random.default_rng(0).normal(size=(3000, 64)))
    data = bytearray(path.read_bytes())
    mid = len(data) // 2 // 4096 * 4096
    data[mid:mid + 4096] = b"\xff" * 4096
    path.write_bytes(bytes(data))
    with pytest.raises(sqlite3.DatabaseError, match=rf"{path}: the embedding cache is damaged "
                       r"\(.*malformed.*\).*\.recover.*delete it to rebuild \(its texts"):
        with EmbeddingCache(path) as cache:
            cache.get_many("enc", keys)
            cache.count()


def test_select_in_asks_in_chunks(tmp_path):
    class Numbers(SQLiteCache):
        kind = "number table"
        schema = ("CREATE TABLE IF NOT EXISTS n (tag TEXT, k INTEGER)",)

    with Numbers(tmp_path / "n.sqlite") as t:
        with t.db:
            t.db.executemany("INSERT INTO n VALUES (?, ?)", [("x", i) for i in range(25)] + [("y", 3)])
        rows = list(select_in(t.db, "SELECT k FROM n WHERE tag=? AND k IN ({})", ["x"], list(range(0, 30, 2)), 4))
        assert sorted(k for (k,) in rows) == list(range(0, 25, 2))
    with pytest.raises(sqlite3.DatabaseError, match="not a usable number table"):
        connect(tmp_path, ["SELECT 1"], "number table")         # a folder is no database


def test_stale_temps_of_a_dead_process_are_removed(tmp_path):
    """A killed writer's temp folder/file (its pid gone) goes when the output is next
    written; a live process's temp stays."""
    import subprocess
    import sys

    from party.io import atomic_dir, write_text

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale_dir = tmp_path / f".prepared.{dead}.abc123.tmp"
    (stale_dir / "synthetic").mkdir(parents=True)
    stale_file = tmp_path / f".index.json.{dead}.x1.json.tmp"
    stale_file.write_text("half")
    stale_gif = tmp_path / f".a.gif.{dead}.x2.tmp.gif"
    stale_gif.write_text("half")
    legacy = tmp_path / ".prepared.q9z8.tmp"           # written before temps carried a pid
    legacy.mkdir()
    live = tmp_path / f".prepared.{os.getpid()}.zzz.tmp"
    live.mkdir()
    with atomic_dir(tmp_path / "prepared") as d:
        (d / "x").write_text("1")
    write_text(tmp_path / "index.json", "{}")
    write_text(tmp_path / "a.gif", "gif")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(["prepared", "index.json", "a.gif", live.name]), left
