"""The aligned multi-stream dataset the generator trains on (SPEC §2-3).

One sample = one (clip, caption) pair: every caption of every clip of a split of the prepared
index is its own sample (timed captions are clips of their own, mirrored motions ``M...`` too).
A sample holds

- ``text_emb`` (D,): the caption's embedding (``party embed_texts``),
- ``part_emb`` {part: (D,)}: the embeddings of its part texts (``party cache_part_texts``),
- ``no_movement`` {part: bool}: the part text is ``no_movement_text`` (case-insensitive, stripped),
- ``codes`` {stream: (n_s,)} / ``lengths`` {stream: n_s}: the clip's codes in every token store
  (``party extract_tokens``), without END (the model appends END = K_s itself; PAD = K_s + 1).

Cropping: a stream holds at most ``max_tokens - 1`` codes (one position is left for END).
When any stream is longer, every stream is cut to the same span of frames from the clip's start,
so the streams stay time-aligned: with F = min_s (max_tokens - 1) * w_s frames (w_s =
``meta["window"]`` of the stream's store), stream s keeps ``min(n_s, F // w_s)`` codes; for
holistic codes of window w_h and part codes of window w_p >= w_h that is n_h = max_tokens - 1
and n_p = floor(n_h * w_h / w_p). A cropped sample still ends in END (the motion's tail is
simply not learned); crops are deterministic (the head is kept).

Texts are embedded once: all distinct captions in one ``EmbeddingStore.get`` call and all
distinct part texts in another, at construction; codes are read once per clip at construction
too, so a missing clip or embedding fails before training starts.

Token corruption (T2M-GPT, ``generator.corruption``): ``corrupt_codes`` replaces a random
fraction of the *teacher-forcing inputs*; the targets must stay the clean codes.

    ds = build_generator_data(cfg, "train")
    loader = DataLoader(ds, batch_size=..., collate_fn=partial(collate_generator, pad=ds.pad))
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from party.tokenizers.tokens import TokenStore
from party.text.store import EmbeddingStore


def pad_tokens(stores: Mapping[str, TokenStore]) -> dict[str, int]:
    """PAD id per stream: K_s + 1 (END = K_s, codes in [0, K_s))."""
    return {s: int(st.meta["codebook_size"]) + 1 for s, st in stores.items()}


def end_tokens(stores: Mapping[str, TokenStore]) -> dict[str, int]:
    """END id per stream: K_s."""
    return {s: int(st.meta["codebook_size"]) for s, st in stores.items()}


def crop_lengths(lengths: Mapping[str, int], windows: Mapping[str, int], max_codes: int) -> dict[str, int]:
    """Codes kept per stream when every stream holds at most ``max_codes``, time-aligned (module doc)."""
    if all(n <= max_codes for n in lengths.values()):
        return dict(lengths)
    frames = min(max_codes * windows[s] for s in lengths)
    return {s: min(n, frames // windows[s]) for s, n in lengths.items()}


def is_no_movement(text: str, no_movement_text: str) -> bool:
    return text.strip().lower() == no_movement_text.strip().lower()


class GeneratorDataset(Dataset):
    """(clip, caption) samples of ``split`` with their embeddings and time-aligned codes.

    stores: {stream: TokenStore} in stream order (holistic first); parts: the part-text names
    (``part_texts.parts``); part_texts: {caption: {part: text}} (``load_part_texts``).
    """

    def __init__(self, ctx, stores: Mapping[str, TokenStore], embeddings: EmbeddingStore,
                 part_texts: Mapping[str, Mapping[str, str]], split: str, parts: Sequence[str],
                 no_movement_text: str, max_tokens: int, multi_level: bool = False):
        if int(max_tokens) < 2:
            raise ValueError(f"max_tokens = {max_tokens}: needs room for one code and END "
                             "(generator.model.max_tokens >= 2)")
        if not stores:
            raise ValueError("no token stores (generator.streams is empty)")
        self.split, self.parts = split, [str(p) for p in parts]
        self.streams = list(stores)
        self.max_tokens = int(max_tokens)
        self.no_movement_text = str(no_movement_text)
        for s, st in stores.items():
            if st.meta["stream"] != s:
                raise ValueError(f"{st.root}: holds the {st.meta['stream']!r} tokens, expected "
                                 f"{s!r}; check generator.tokens_dir or rerun `party extract_tokens`")
            if st.levels != 1 and not multi_level:
                raise ValueError(f"{st.root}: {st.levels} code levels per token; this method "
                                 "predicts one code per token (use a one-level tokenizer and rerun "
                                 "`party extract_tokens`)")
        self.windows = {s: int(st.meta["window"]) for s, st in stores.items()}
        self.codebook_sizes = {s: int(st.meta["codebook_size"]) for s, st in stores.items()}
        self.pad = pad_tokens(stores)
        self.end = end_tokens(stores)

        index = ctx.index
        clips = index.clips(split)
        if not clips:
            raise ValueError(f"{index.path}: no clips in split {split!r}; rerun `party prepare`")

        # codes, read once per clip (and cropped) -- a missing clip fails here
        self.clip_ids: list[str] = []
        self._codes: list[dict[str, np.ndarray]] = []
        samples: list[tuple[int, str]] = []            # (clip number, caption)
        for clip in clips:
            raw = {}
            for s, st in stores.items():
                if clip["id"] not in st:
                    raise KeyError(f"{st.root}: no {s!r} tokens for clip {clip['id']!r} of "
                                   f"{index.path}; rerun `party extract_tokens`")
                raw[s] = st.get(clip["id"])
            keep = crop_lengths({s: len(c) for s, c in raw.items()}, self.windows, self.max_tokens - 1)
            self._codes.append({s: raw[s][:keep[s]] for s in self.streams})
            for cap in clip["captions"]:
                samples.append((len(self.clip_ids), cap["caption"]))
            self.clip_ids.append(clip["id"])
        if not samples:
            raise ValueError(f"{index.path}: clips of split {split!r} have no captions; rerun `party prepare`")
        self._clip_of = np.array([c for c, _ in samples], dtype=np.int64)
        self.captions = [cap for _, cap in samples]

        # part texts of every caption
        missing = [c for c in dict.fromkeys(self.captions) if c not in part_texts]
        if missing:
            raise KeyError(f"{len(missing)} caption(s) of split {split!r} have no part texts "
                           f"(first: {missing[0]!r}); rerun `party cache_part_texts`")
        caps = list(dict.fromkeys(self.captions))
        part_of = {c: {p: str(part_texts[c][p]) for p in self.parts} for c in caps}
        ptexts = list(dict.fromkeys(part_of[c][p] for c in caps for p in self.parts))

        # embeddings: one get for the captions, one for the part texts
        for what, texts in (("caption", caps), ("part text", ptexts)):
            absent = [t for t in texts if t not in embeddings]
            if absent:
                raise KeyError(f"{embeddings.path}: {len(absent)} {what}(s) of split {split!r} have "
                               f"no embedding (first: {absent[0]!r}); rerun `party embed_texts`")
        self._cap_emb = torch.from_numpy(np.array(embeddings.get(caps), dtype=np.float32))
        self._part_emb = torch.from_numpy(np.array(embeddings.get(ptexts), dtype=np.float32))
        cap_row = {c: i for i, c in enumerate(caps)}
        prow = {t: i for i, t in enumerate(ptexts)}
        self._cap_of = np.array([cap_row[c] for c in self.captions], dtype=np.int64)
        self._part_of = {p: np.array([prow[part_of[c][p]] for c in self.captions], dtype=np.int64)
                         for p in self.parts}
        self._no_move = {p: np.array([is_no_movement(part_of[c][p], self.no_movement_text)
                                      for c in self.captions], dtype=bool) for p in self.parts}

    @property
    def caption_embeddings(self) -> torch.Tensor:
        """(distinct captions, D) embeddings of this split's captions."""
        return self._cap_emb

    @property
    def dim(self) -> int:
        return int(self._cap_emb.shape[1])

    def __len__(self) -> int:
        return len(self.captions)

    def lengths(self, stream: str) -> np.ndarray:
        """Codes per sample of ``stream`` (after cropping), e.g. for length bucketing."""
        n = np.array([len(c[stream]) for c in self._codes], dtype=np.int64)
        return n[self._clip_of]

    def __getitem__(self, i: int) -> dict:
        clip = int(self._clip_of[i])
        codes = self._codes[clip]
        return {"clip_id": self.clip_ids[clip], "caption": self.captions[i],
                "text_emb": self._cap_emb[self._cap_of[i]],
                "part_emb": {p: self._part_emb[self._part_of[p][i]] for p in self.parts},
                "no_movement": {p: bool(self._no_move[p][i]) for p in self.parts},
                "codes": {s: torch.from_numpy(codes[s].astype(np.int64)) for s in self.streams},
                "lengths": {s: int(len(codes[s])) for s in self.streams}}


def collate_generator(items: Sequence[dict], pad: Mapping[str, int]) -> dict:
    """Batch of ``GeneratorDataset`` items: codes right-padded with ``pad[stream]`` (= K_s + 1),
    no END token; the layout the generator consumes (module doc)."""
    if not items:
        raise ValueError("collate_generator: empty batch")
    streams, parts = list(items[0]["codes"]), list(items[0]["part_emb"])
    B = len(items)
    codes, lengths = {}, {}
    for s in streams:
        n = torch.tensor([it["lengths"][s] for it in items], dtype=torch.long)
        out = torch.full((B, int(n.max()), *items[0]["codes"][s].shape[1:]), int(pad[s]), dtype=torch.long)
        for b, it in enumerate(items):
            out[b, :n[b]] = it["codes"][s]
        codes[s], lengths[s] = out, n
    return {"text_emb": torch.stack([it["text_emb"] for it in items]).float(),
            "part_emb": {p: torch.stack([it["part_emb"][p] for it in items]).float() for p in parts},
            "no_movement": {p: torch.tensor([it["no_movement"][p] for it in items], dtype=torch.bool)
                            for p in parts},
            "codes": codes, "lengths": lengths,
            "clip_id": [it["clip_id"] for it in items], "caption": [it["caption"] for it in items]}


def corrupt_codes(codes: torch.Tensor, lengths: torch.Tensor, K: int, max_prob: float,
                  generator: torch.Generator | None) -> torch.Tensor:
    """T2M-GPT token corruption: a copy of ``codes`` (B, L) (or (B, L, Q): each code of a row on its
    own) in which each code of a position < ``lengths[b]`` is replaced, with probability p_b ~ U[0, max_prob] drawn per sample, by a random code in
    [0, K). Positions past the length (PAD) are untouched. Apply it to the teacher-forcing
    *inputs* only; the targets must stay the clean codes. Draws come from ``generator``
    (on any device; None: torch's default generator), so a seeded generator reproduces them."""
    if not 0.0 <= float(max_prob) <= 1.0:
        raise ValueError(f"corruption probability {max_prob} outside [0, 1] (generator.corruption.prob)")
    if codes.ndim not in (2, 3) or lengths.shape != codes.shape[:1]:
        raise ValueError(f"codes {tuple(codes.shape)} / lengths {tuple(lengths.shape)}: expected (B, L[, Q]) / (B,)")
    B, L = codes.shape[:2]
    extra = (1,) * (codes.ndim - 2)
    dev = generator.device if generator is not None else torch.device("cpu")
    p = torch.rand(B, 1, *extra, generator=generator, device=dev) * float(max_prob)
    hit = torch.rand(codes.shape, generator=generator, device=dev) < p
    rnd = torch.randint(0, int(K), codes.shape, generator=generator, device=dev)
    hit, rnd = hit.to(codes.device), rnd.to(codes.device, codes.dtype)
    inside = torch.arange(L, device=codes.device)[None] < lengths.to(codes.device)[:, None]
    hit &= inside.view(B, L, *extra)
    return torch.where(hit, rnd, codes)


class LengthBucketBatchSampler(Sampler[list[int]]):
    """Batches of samples of similar length: each epoch shuffles the samples, cuts them into pools
    of ``batch_size * pool`` samples, sorts each pool by length and cuts it into batches, then
    shuffles the batches. ``seed`` + the epoch number (``set_epoch``) fix the order. ``pool`` 1
    gives uniform random batches (each ``batch_size`` run of the shuffled samples is one batch).

    Under DDP (``torch.distributed`` initialised with world size W > 1) rank r takes batches
    r, r + W, ... of that order, every rank the same number (the last incomplete round is dropped),
    so each optimizer step averages W batches of one epoch's order; Lightning must not inject its
    own sampler (``use_distributed_sampler=False``).

    ``follow(step)`` ties the order to a step counter instead (``train_generator`` passes the
    trainer's global step): every iterator starts at batch ``step()`` of the endless sequence
    epoch 0, epoch 1, ... So a run resumed from a checkpoint, mid-epoch or not, trains on the
    batches the uninterrupted run would have (Lightning restarts a mid-epoch loader at its
    epoch's first batch, and calls ``set_epoch`` only on a loader's ``sampler`` and
    ``batch_sampler.sampler``, never on a batch sampler: without ``follow`` every epoch would
    repeat epoch 0's order)."""

    def __init__(self, lengths: Sequence[int], batch_size: int, pool: int, seed: int, drop_last: bool):
        if int(batch_size) < 1 or int(pool) < 1:
            raise ValueError(f"batch_size {batch_size} and pool {pool} must be >= 1")
        self.lengths = np.asarray(lengths, dtype=np.int64)
        self.batch_size, self.pool, self.seed, self.drop_last = int(batch_size), int(pool), int(seed), bool(drop_last)
        self.epoch = 0
        self._step: Callable[[], int] | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def follow(self, step: Callable[[], int]) -> None:
        """Start every iterator at batch ``step()`` (per rank) of the epoch-by-epoch order."""
        self._step = step

    def _batches(self) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(len(self.lengths))
        size = self.batch_size * self.pool
        batches = []
        for start in range(0, len(order), size):
            chunk = order[start:start + size]
            chunk = chunk[np.argsort(self.lengths[chunk], kind="stable")]
            for b in range(0, len(chunk), self.batch_size):
                batch = chunk[b:b + self.batch_size]
                if len(batch) == self.batch_size or not self.drop_last:
                    batches.append([int(i) for i in batch])
        return [batches[i] for i in rng.permutation(len(batches))]

    @staticmethod
    def _rank_world() -> tuple[int, int]:
        import torch.distributed as dist
        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
        return 0, 1

    def __iter__(self) -> Iterator[list[int]]:
        skip = 0
        if self._step is not None:
            self.epoch, skip = divmod(int(self._step()), len(self))
        batches = self._batches()
        rank, world = self._rank_world()
        if world > 1:
            batches = batches[rank:len(batches) - len(batches) % world:world]
        return iter(batches[skip:])

    def __len__(self) -> int:
        full, rest = divmod(len(self.lengths), self.batch_size * self.pool)
        tail = rest // self.batch_size if self.drop_last else -(-rest // self.batch_size)
        return (full * self.pool + tail) // self._rank_world()[1]


def open_token_stores(tokens_dir: str | Path, streams: Sequence[str]) -> dict[str, TokenStore]:
    return {str(s): TokenStore.open(Path(tokens_dir) / str(s)) for s in streams}


def build_generator_data(cfg, split: str, streams: Sequence[str] | None = None,
                         multi_level: bool = False) -> GeneratorDataset:
    """``GeneratorDataset`` of ``split`` wired from the config: ``paths.prepared`` (index),
    ``generator.tokens_dir`` / ``streams`` (token stores; None: ``generator.streams``), ``text.embeddings_dir``
    (current encoder), ``text.part_texts_path`` / ``part_texts.parts``,
    ``generator.loss.no_movement_text`` and ``generator.model.max_tokens``; ``multi_level``: rows of
    Q codes per token allowed (a method that reads them)."""
    from party.data.context import load_context
    from party.text.cache import load_part_texts

    g = cfg.generator
    parts = [str(p) for p in cfg.part_texts.parts]
    return GeneratorDataset(load_context(cfg), open_token_stores(g.tokens_dir, g.streams if streams is None else streams),
                            EmbeddingStore.open(cfg.text.embeddings_dir),
                            load_part_texts(cfg.text.part_texts_path, parts), split, parts,
                            str(g.loss.no_movement_text), int(g.model.max_tokens), multi_level)
