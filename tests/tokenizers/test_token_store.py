"""TokenStore: one code per token (N,) and Q code levels per token (N, Q); stores without
``levels`` (written before it existed) still open."""
from __future__ import annotations

import json

import numpy as np
import pytest

from party.tokenizers.tokens import TokenStore, write_token_store

META = {"stream": "holistic", "window": 4, "tail": "crop", "codebook_size": 16}


def _sequences(rng, levels: int):
    shapes = [(5,), (3,), (0,), (7,)] if levels == 1 else [(5, levels), (3, levels), (0, levels), (7, levels)]
    return [({"motion": f"m{i}", "start": 0, "end": 4 * s[0]}, rng.integers(0, 16, s)) for i, s in enumerate(shapes)]


@pytest.mark.parametrize("levels", [1, 2, 3])
def test_round_trip(tmp_path, levels):
    seqs = _sequences(np.random.default_rng(levels), levels)
    keys = {"a": 0, "a_alias": 0, "b": 1, "c": 2, "d": 3}
    meta = write_token_store(tmp_path / "s", seqs, keys, {**META, "levels": levels})
    store = TokenStore.open(tmp_path / "s")
    assert store.levels == meta["levels"] == levels
    assert store.codes.shape == ((15,) if levels == 1 else (15, levels))
    assert store.codes.dtype == np.int16 and meta["n_codes_total"] == 15 and meta["n_entries"] == 4
    for key, entry in keys.items():
        got = store.get(key)
        assert got.dtype == np.int64 and np.array_equal(got, seqs[entry][1]), key
    # levels taken from the codes when the caller does not say
    meta2 = write_token_store(tmp_path / "t", seqs, keys, META)
    assert meta2["levels"] == levels and meta2["sha256"] == meta["sha256"]


def test_one_level_bytes_unchanged(tmp_path):
    """Q = 1 writes the same codes.npy (and fingerprint) as before levels existed."""
    import hashlib
    seqs = _sequences(np.random.default_rng(0), 1)
    meta = write_token_store(tmp_path / "s", seqs, {"a": 0}, META)
    flat = np.concatenate([c for _, c in seqs]).astype(np.int16)
    assert meta["sha256"] == hashlib.sha256(flat.tobytes()).hexdigest()
    assert np.load(tmp_path / "s" / "codes.npy").shape == (15,)


def test_store_without_levels_opens_as_one_level(tmp_path):
    seqs = _sequences(np.random.default_rng(0), 1)
    write_token_store(tmp_path / "s", seqs, {"a": 0, "d": 3}, META)
    idx_path = tmp_path / "s" / "index.json"
    index = json.loads(idx_path.read_text())
    del index["meta"]["levels"]                       # what extract_tokens wrote before
    idx_path.write_text(json.dumps(index))
    store = TokenStore.open(tmp_path / "s")
    assert store.levels == 1 and np.array_equal(store.get("d"), seqs[3][1])


def test_shape_errors(tmp_path):
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="expected"):          # (n, 1): one level is (n,)
        write_token_store(tmp_path / "a", [({"motion": "m"}, rng.integers(0, 16, (4, 1)))], {}, META)
    with pytest.raises(ValueError, match="expected"):          # levels disagree between entries
        write_token_store(tmp_path / "b", [({"motion": "m"}, rng.integers(0, 16, (4, 2))),
                                           ({"motion": "n"}, rng.integers(0, 16, (4, 3)))], {}, META)
    with pytest.raises(ValueError, match="expected"):          # meta says 2 levels, codes have 1
        write_token_store(tmp_path / "c", [({"motion": "m"}, rng.integers(0, 16, 4))], {}, {**META, "levels": 2})
    with pytest.raises(ValueError, match="outside"):
        write_token_store(tmp_path / "d", [({"motion": "m"}, np.array([[0, 16]]))], {}, META)
    # a store whose codes.npy does not match its index.json
    write_token_store(tmp_path / "e", [({"motion": "m"}, rng.integers(0, 16, (4, 2)))], {"m": 0}, META)
    index = json.loads((tmp_path / "e" / "index.json").read_text())
    index["meta"]["levels"] = 1
    (tmp_path / "e" / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="rerun"):
        TokenStore.open(tmp_path / "e")


def test_empty_store(tmp_path):
    meta = write_token_store(tmp_path / "s", [], {}, {**META, "levels": 2})
    store = TokenStore.open(tmp_path / "s")
    assert meta["levels"] == 2 and store.codes.shape == (0, 2) and len(store) == 0


def test_codes_changed_after_writing_are_refused(tmp_path):
    """Same shape, other codes (an edit, bit rot): refused at open, naming codes.npy, not later as an
    out-of-range code inside training."""
    seqs = _sequences(np.random.default_rng(0), 1)
    write_token_store(tmp_path / "s", seqs, {"a": 0}, META)
    path = tmp_path / "s" / "codes.npy"
    for value, outside in ((3, 0), (955, 1)):                  # in the codebook, and outside it
        codes = np.load(path)
        codes[2] = value if codes[2] != value else value + 1
        np.save(path, codes)
        with pytest.raises(ValueError, match=rf"codes.npy: the codes differ from those extract_tokens wrote "
                                             rf"\(sha256 in index.json; {outside} outside the codebook \[0, 16\)\)"):
            TokenStore.open(tmp_path / "s")
        write_token_store(tmp_path / "s", seqs, {"a": 0}, META)
    assert np.array_equal(TokenStore.open(tmp_path / "s").get("a"), seqs[0][1])
