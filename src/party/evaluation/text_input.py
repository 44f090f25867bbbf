"""Text inputs of the evaluator's text encoder: word vectors + POS one-hot.

The reference evaluator (Guo et al. 2022) reads each caption as ``word/POS``
tokens, looks every word up in GloVe (300-d, ``our_vab_*`` files), adds a
15-way POS one-hot (with "VIP" overrides for motion words), wraps the
sentence in ``sos``/``eos`` and pads with ``unk`` to ``max_text_len + 2``.

Three featurisers share that interface, ``f(captions, tokens) ->
(word_embs (B, L, d), pos_ohot (B, L, 15), lengths (B,))``:

- ``WordVectorizer`` over GloVe (``text_input: glove``; the reference one),
- ``WordVectorizer`` over a word table built offline from the text encoder
  (``text_input: words``; default): every vocabulary word is encoded alone by
  ``encode_tokens`` and its token features are mean-pooled. The table is
  stored in the evaluator checkpoint, so the evaluator never changes when
  the text encoder does, and POS tags line up with words exactly as in the
  reference;
- ``ContextualTokens`` (``text_input: tokens``): the text encoder's
  contextual per-token features of the whole caption, POS one-hot left at
  zero (encoder tokens do not align with ``word/POS`` tokens).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from party.io import load_npy

POS_ENUMERATOR = {
    "VERB": 0, "NOUN": 1, "DET": 2, "ADP": 3, "NUM": 4, "AUX": 5, "PRON": 6, "ADJ": 7, "ADV": 8,
    "Loc_VIP": 9, "Body_VIP": 10, "Obj_VIP": 11, "Act_VIP": 12, "Desc_VIP": 13, "OTHER": 14,
}  # fmt: skip
VIP_WORDS = {
    "Loc_VIP": ("left", "right", "clockwise", "counterclockwise", "anticlockwise", "forward", "back",
                "backward", "up", "down", "straight", "curve"),
    "Body_VIP": ("arm", "chin", "foot", "feet", "face", "hand", "mouth", "leg", "waist", "eye", "knee",
                 "shoulder", "thigh"),
    "Obj_VIP": ("stair", "dumbbell", "chair", "window", "floor", "car", "ball", "handrail", "baseball",
                "basketball"),
    "Act_VIP": ("walk", "run", "swing", "pick", "bring", "kick", "put", "squat", "throw", "hop", "dance",
                "jump", "turn", "stumble", "dance", "stop", "sit", "lift", "lower", "raise", "wash", "stand",
                "kneel", "stroll", "rub", "bend", "balance", "flap", "jog", "shuffle", "lean", "rotate", "spin",
                "spread", "climb"),
    "Desc_VIP": ("slowly", "carefully", "fast", "careful", "slow", "quickly", "happy", "angry", "sad",
                 "happily", "angrily", "sadly"),
}  # fmt: skip
_VIP_OF = {w: k for k, ws in VIP_WORDS.items() for w in ws}
SPECIAL_WORDS = ("sos", "eos", "unk")


def pos_dim() -> int:
    return len(POS_ENUMERATOR)


def caption_tokens(caption: str, tokens: Sequence[str] | None) -> list[str]:
    """``word/POS`` tokens of a caption; without tags, words of the caption tagged OTHER."""
    if tokens:
        return [t if "/" in t else f"{t}/OTHER" for t in tokens]
    return [f"{w.strip('.,;:!?').lower()}/OTHER" for w in caption.split() if w.strip(".,;:!?")]


def pad_tokens(tokens: Sequence[str], max_text_len: int) -> tuple[list[str], int]:
    """Reference treatment: sos + tokens[:max_len] + eos, padded with unk to max_len + 2."""
    toks = ["sos/OTHER", *list(tokens)[:max_text_len], "eos/OTHER"]
    n = len(toks)
    return toks + ["unk/OTHER"] * (max_text_len + 2 - n), n


class _NoGlobals(pickle.Unpickler):
    """Unpickles lists, dicts, str and numbers; any class or function (a global) is refused."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(f"it names the global {module}.{name}")


def load_plain_pickle(path: Path, check: Callable[[object], bool], expected: str):
    """A pickle of plain data (no globals: nothing in it runs), checked to be ``expected``."""
    try:
        with open(path, "rb") as fh:
            obj = _NoGlobals(fh).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError, KeyError,
            AttributeError, RecursionError) as e:
        raise ValueError(f"{path}: NOT loaded: a GloVe file must be a pickle of plain data ({expected}), "
                         f"but {e}") from None
    if not check(obj):
        raise ValueError(f"{path}: a GloVe file must hold {expected}, got {type(obj).__name__}")
    return obj


def _str_list(x) -> bool:
    return isinstance(x, list) and all(isinstance(w, str) for w in x)


def _str_int_dict(x) -> bool:
    return isinstance(x, dict) and all(isinstance(k, str) and type(v) is int for k, v in x.items())


class WordVectorizer:
    """word/POS -> (word vector, POS one-hot), exactly as the reference ``WordVectorizer``."""

    def __init__(self, words: Sequence[str], vectors: np.ndarray, max_text_len: int = 20):
        vectors = np.asarray(vectors, dtype=np.float32)
        if vectors.ndim != 2 or len(words) != vectors.shape[0]:
            raise ValueError(f"word table: {len(words)} words but vectors of shape {vectors.shape}")
        self.words = list(words)
        self.vectors = vectors
        self.row = {w: i for i, w in enumerate(self.words)}
        if "unk" not in self.row:
            raise ValueError("word table has no 'unk' entry")
        self.max_text_len = max_text_len
        self.dim = vectors.shape[1]

    @classmethod
    def from_glove(cls, glove_dir: str | Path, prefix: str = "our_vab", max_text_len: int = 20) -> WordVectorizer:
        d = Path(glove_dir)
        files = [d / f"{prefix}_data.npy", d / f"{prefix}_words.pkl", d / f"{prefix}_idx.pkl"]
        for f in files:
            if not f.is_file():
                raise FileNotFoundError(f"{f}: GloVe file of the reference evaluator not found")
        vectors = load_npy(files[0], "the reference evaluator's release", "GloVe vectors")
        words = load_plain_pickle(files[1], _str_list, "a list of str")
        word2idx = load_plain_pickle(files[2], _str_int_dict, "a dict str -> int")
        rows = [word2idx.get(w, -1) for w in words]
        bad = [w for w, r in zip(words, rows) if not 0 <= r < len(vectors)]
        if bad:
            raise ValueError(f"{files[2]}: {len(bad)} words of {files[1].name} have no row of "
                             f"{files[0].name} (e.g. {bad[0]!r})")
        return cls(words, vectors[rows], max_text_len)

    def lookup(self, token: str) -> tuple[int, int]:
        word, _, pos = token.partition("/")
        if word in self.row:
            tag = _VIP_OF.get(word, pos)
            return self.row[word], POS_ENUMERATOR.get(tag, POS_ENUMERATOR["OTHER"])
        return self.row["unk"], POS_ENUMERATOR["OTHER"]

    def __call__(self, captions: Sequence[str], tokens: Sequence[Sequence[str] | None]):
        rows, tags, lens = [], [], []
        for cap, tok in zip(captions, tokens, strict=True):
            padded, n = pad_tokens(caption_tokens(cap, tok), self.max_text_len)
            rt = [self.lookup(t) for t in padded]
            rows.append([r for r, _ in rt])
            tags.append([p for _, p in rt])
            lens.append(n)
        word = torch.from_numpy(self.vectors[np.asarray(rows)])
        pos = torch.nn.functional.one_hot(torch.as_tensor(tags), pos_dim()).float()
        return word, pos, torch.as_tensor(lens, dtype=torch.long)


def _tensor(x) -> torch.Tensor:
    """CPU copy of encoder output (a clone: encoders may return inference-mode tensors,
    which autograd cannot save for backward)."""
    return (x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))).detach().cpu().clone()


class ContextualTokens:
    """Per-token features of the whole caption from the offline text encoder (POS left at zero)."""

    def __init__(self, encoder, max_tokens: int | None = None):
        self.encoder = encoder
        self.max_tokens = max_tokens

    def __call__(self, captions: Sequence[str], tokens=None):
        with torch.no_grad():
            feats, lens = self.encoder.encode_tokens(list(captions))
        feats, lens = _tensor(feats).float(), _tensor(lens).long()
        if self.max_tokens:
            feats, lens = feats[:, : self.max_tokens], lens.clamp(max=self.max_tokens)
        pos = torch.zeros(*feats.shape[:2], pos_dim())
        return feats, pos, lens.clamp(min=1)


def vocabulary(token_lists) -> list[str]:
    """Sorted set of words in ``word/POS`` token lists, plus sos/eos/unk."""
    words = {t.partition("/")[0] for toks in token_lists for t in toks}
    return sorted(words | set(SPECIAL_WORDS))


def build_word_table(encoder, words: Sequence[str], batch_size: int = 256) -> np.ndarray:
    """Encode each word alone with the text encoder; mean-pool its token features -> (V, d)."""
    from tqdm import tqdm

    out = []
    for i in tqdm(range(0, len(words), batch_size), desc="word table", disable=len(words) < 4 * batch_size):
        with torch.no_grad():
            feats, lens = encoder.encode_tokens(list(words[i : i + batch_size]))
        feats, lens = _tensor(feats).float(), _tensor(lens).long()
        mask = (torch.arange(feats.shape[1])[None, :] < lens[:, None]).float()[..., None]
        out.append((feats * mask).sum(1) / mask.sum(1).clamp(min=1))
    return torch.cat(out).numpy().astype(np.float32)
