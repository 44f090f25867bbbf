"""Typed schema of the composed configuration (``conf/`` -> ``params.yaml``).

One dataclass per config group, nested as the composed config is: :class:`Config`
is the root (``seed``, ``progress``, ``objective``, ``paths`` and the groups ``dataset``,
``tracking``, ``trainer``, ``text``, ``part_texts``, ``vqvae``, ``evaluator``,
``eval``). The schema names and types keys; **values live in conf/ only**, so no
field carries a value default: a field is either required (``MISSING``; a nested
group is built from its own all-``MISSING`` dataclass) or ``Optional[...] = None``
for a key that only some group options have (``dataset.synthetic``, ``dataset.bvh``, the CLIP-only ``text.*`` keys, the OpenAI-only
``part_texts.*`` keys, the per-stream ``vqvae.tokenizers.<stream>`` overrides).
A required key may be nullable (``Optional[int] = MISSING``: present, may be null).

:func:`validate` checks a composed config (or ``params.yaml``) against the schema
and raises :class:`ConfigError` naming the dotted key, e.g.::

    params.yaml: vqvae.train.max_steps: 'abc' is not an int
    conf: unknown key vqvae.train.bogus (not in the schema; typo?)

Checks: unknown keys, missing required keys, types (strict: a quoted ``'5'`` is not
an int, ``1`` is not a bool; an int is a float), ranges where a stage cannot run outside
them (``_range``: counts >= 1, probabilities, positive scales; bounds, not values),
``null`` only where the schema says Optional, and the few genuine unions (``trainer.devices``: int | str | list of int;
``eval.sources.generated``: str | list of str), and names (``NAME_KEYS``: streams, parts and
methods become folder names and dvc.yaml command words, so each is a plain name,
``party.names``). ``???`` (the conf's own "must be set" marker, e.g. ``dataset.root`` of a
real dataset) is accepted: OmegaConf raises, naming the key, when a stage reads it. The returned config holds the values exactly
as given (resolved, never coerced or filled in), so params.yaml, config hashes and
``cfg.get(key, default)`` lookups behave as before.

Where validation runs: ``party.config.compose`` (hence ``party params``, ``party
params --check`` and every test composing ``conf/``) and ``party.config.load_params``;
stages call ``validate(cfg, "params.yaml")`` at start. ``dvc exp run -S ...``
composes ``conf/`` through Hydra without importing ``party``, so a bad ``-S`` value
there is written to params.yaml unchecked and caught when the first stage starts.
The schema is deliberately not attached to Hydra's composition (ConfigStore +
defaults lists): Hydra would then coerce values while composing (``fps: 20`` ->
``20.0``) and add ``null`` for every absent optional key, changing params.yaml, and
conf/ would stop composing wherever the plugin is not installed.

The dataclasses are valid OmegaConf structured configs (unions are typed ``Any``),
so ``OmegaConf.structured(Config)`` builds, but ``validate`` walks them itself:
OmegaConf 2.3 coerces (``'5'`` -> 5, ``1`` -> true), has no unions, and rejects an int
in a ``List[float]`` inside a ``Dict`` (``limits_deg: {elbow: [0, 150]}``).
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import typing
from dataclasses import dataclass, field
from typing import Any, Dict, List, Literal, Mapping, Optional

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

__all__ = ["ConfigError", "Config", "validate", "SCHEMA_GROUPS", "step_keys"]


class ConfigError(ValueError):
    """A config does not match the schema; the message names the dotted key."""

    def __init__(self, message: str, key: str = ""):
        super().__init__(message)
        self.key = key


def _group(cls):
    """A required nested group: the node exists with every leaf ``MISSING``."""
    return field(default_factory=cls)


def _union(*types):
    """A required key of one of ``types`` (OmegaConf 2.3 has no Union: typed Any, checked here)."""
    return field(default=MISSING, metadata={"union": types})


def _range(lo: float | None = None, hi: float | None = None, *, above: bool = False, below: bool = False):
    """A required number in [lo, hi] (``above``: > lo, ``below``: < hi; None: unbounded there).
    Only the bounds without which a stage cannot run are stated (counts of at least one,
    probabilities, positive scales), so a bad value fails here, naming the key, instead of deep
    in a stage (0 replications, a batch of 0)."""
    return field(default=MISSING, metadata={"range": (lo, hi, above, below)})


def _choice(*values: str):
    """A required string, one of ``values`` (OmegaConf 2.3 structured configs cannot hold
    ``Literal``: typed str, checked here; a family's own ``Config`` may use ``Literal``)."""
    return field(default=MISSING, metadata={"choices": values})


def _off_step(f):
    """Mark a field as not changing what a training step computes (a run may resume across a
    change to it): it is left out of resume keys (``step_keys``)."""
    kw = {"default": f.default} if f.default is not dataclasses.MISSING else {"default_factory": f.default_factory}
    return field(**kw, metadata={**f.metadata, "step": False})


def step_keys(cls, value: Mapping) -> dict:
    """``value`` (a group of ``cls``) without the keys marked ``_off_step``: what changes a step."""
    off = {f.name for f in dataclasses.fields(cls) if f.metadata.get("step") is False}
    return {k: v for k, v in dict(value).items() if k not in off}


def _people_only(f):
    """Mark a ``generator.generate`` field as read only for people's texts (not a param of the
    pipeline's ``generate`` stage: ``party.pipeline_params``)."""
    return field(default=f.default, metadata={**f.metadata, "people": True})


class MethodEntry:
    """Schema type of ``generator.methods.<m>``: the dataclass of the family its ``family`` key
    names (``party.methods``: each family declares its own ``Config``)."""


_COUNT = functools.partial(_range, 1)           # a count of at least one (steps, batch sizes, ...)
_SOME = functools.partial(_range, 0)            # zero or more (workers, a pool of 0 = off)
_PROB = functools.partial(_range, 0, 1)         # a probability
_POSITIVE = functools.partial(_range, 0, above=True)


# --------------------------------------------------------------------------- top level

@dataclass
class Paths:
    prepared: str = MISSING


# --------------------------------------------------------------------------- dataset

@dataclass
class Part:
    joints: List[int] = MISSING
    contacts: Optional[str] = None          # leg parts only: that foot's contact channels


@dataclass
class ChannelGroup:                         # a disjoint group of the feature vector (party.motion.parts.group_index)
    joints: List[int] = MISSING
    root: bool = False                      # the root data (4 channels) and joint 0's velocity
    contacts: List[str] = field(default_factory=list)   # left | right: that foot's contact channels


@dataclass
class PartTables:                           # conf/dataset/parts/<skeleton>.yaml
    parts: Dict[str, Part] = MISSING
    streams: List[str] = MISSING            # generation streams, in order
    stream_parts: Dict[str, List[str]] = MISSING   # stream -> its parts (holistic: none)
    coherence: Dict[str, List[int]] = MISSING
    part_tokenizers: List[str] = MISSING    # each body part alone, root first (ParCo-like methods' streams)
    torso: List[int] = MISSING
    # disjoint channel groups that cover the vector once (group tables: H2VQ's coarse / fine groups)
    groups: Dict[str, Dict[str, ChannelGroup]] = field(default_factory=dict)
    # other names of a stream: a tokenizer trained under the alias reads that stream's channels
    aliases: Dict[str, str] = field(default_factory=dict)
    # streams of one channel group each (name -> "<table>.<group>" of groups): a tokenizer per group
    group_streams: Dict[str, str] = field(default_factory=dict)


@dataclass
class SyntheticSplit:
    train: float = MISSING
    val: float = MISSING
    test: float = MISSING


@dataclass
class SpeedWords:
    slow: float = MISSING
    fast: float = MISSING


@dataclass
class SyntheticCaptions:
    per_motion: int = MISSING
    per_segment: int = MISSING
    subjects: List[List[str]] = MISSING     # [words, possessive]
    possessive_prob: float = MISSING
    speed_words: SpeedWords = _group(SpeedWords)
    count_prob: float = MISSING


@dataclass
class SyntheticBody:
    offsets: Dict[str, List[float]] = MISSING   # joint -> parent offset (m)
    ankle_height: float = MISSING
    arm_rest_abduction_deg: float = MISSING
    elbow_rest_deg: float = MISSING
    balance_gain: float = MISSING
    leg_reach: float = MISSING
    limits_deg: Dict[str, List[float]] = MISSING
    torso_radius: float = MISSING
    head_radius: float = MISSING


@dataclass
class Synthetic:                            # dataset=synthetic only
    n_motions: int = MISSING
    seed: int = MISSING
    num_workers: int = MISSING
    mirror: bool = MISSING
    split: SyntheticSplit = _group(SyntheticSplit)
    held_out: List[List[str]] = MISSING     # [arms action, legs action]
    sequence_fraction: float = MISSING
    sequence_kinds: Dict[str, float] = MISSING
    constant_arms: Dict[str, float] = MISSING
    constant_legs: Dict[str, float] = MISSING
    min_segment_s: float = MISSING
    max_segment_cyclic_s: float = MISSING
    transition_frames: int = MISSING
    pad_s: List[float] = MISSING
    std_eps: float = MISSING
    file_sync: bool = MISSING
    captions: SyntheticCaptions = _group(SyntheticCaptions)
    body: SyntheticBody = _group(SyntheticBody)
    # action -> parameter -> number | [lo, hi] | list of choices: free-form tables
    legs: Dict[str, Dict[str, Any]] = MISSING
    arms: Dict[str, Dict[str, Any]] = MISSING


_AXES = ("auto", "x", "y", "z", "-x", "-y", "-z")


@dataclass
class Bvh:                                  # dataset=bvh only (party.data.bvh)
    root: str = MISSING                     # folder of .bvh files and captions
    captions: str = MISSING                 # TSV file, relative to root
    joint_map: Any = _union(str, Dict[str, Any])   # auto | a key of maps | {t2m joint: file joint}
    maps: Dict[str, Dict[str, Any]] = MISSING      # name -> {t2m joint: name | [names] | {between, t}}
    unit: Any = _union(str, float)          # auto | m | cm | mm | inch | metres per file unit
    up_axis: str = _choice(*_AXES)
    forward_axis: str = _choice(*_AXES)
    handedness: str = _choice("right", "left")
    max_floor_offset: float = _POSITIVE()   # m
    mirror: bool = MISSING
    split: SyntheticSplit = _group(SyntheticSplit)
    seed: int = MISSING
    std_eps: float = _POSITIVE()


@dataclass
class Dataset:
    name: str = MISSING
    kind: str = MISSING
    skeleton: str = MISSING
    root: str = MISSING
    fps: float = MISSING
    feat_dim: int = MISSING
    n_joints: int = MISSING
    min_len: int = MISSING
    max_len: int = MISSING
    strict: bool = MISSING
    joints_tol: float = MISSING
    feet_thre: float = MISSING
    parts: PartTables = _group(PartTables)
    synthetic: Optional[Synthetic] = None   # synthetic
    bvh: Optional[Bvh] = None               # bvh


# --------------------------------------------------------------------------- tracking, trainer

@dataclass
class Tracking:
    enabled: bool = MISSING
    experiment: str = MISSING
    uri: Optional[str] = MISSING
    dir: str = MISSING
    parent_run_id: Optional[str] = MISSING
    log_system_metrics: bool = MISSING
    log_model: bool = MISSING
    n_render_samples: int = MISSING


@dataclass
class Trainer:
    accelerator: str = MISSING
    devices: Any = _union(int, str, List[int])  # auto | N | -1 | [ids]
    num_nodes: int = _COUNT()
    strategy: str = MISSING
    precision: str = MISSING
    num_workers: int = _SOME()
    pin_memory: bool = MISSING
    log_every_n_steps: int = _COUNT()
    deterministic: bool = MISSING


# --------------------------------------------------------------------------- text, part_texts

@dataclass
class Text:
    name: str = MISSING
    batch_size: int = MISSING
    batches_per_commit: int = MISSING
    device: str = MISSING
    precision: str = MISSING
    index_path: str = MISSING
    part_texts_path: str = MISSING
    embeddings_dir: str = MISSING
    cache_path: str = MISSING
    # text=minilm
    model_dir: Optional[str] = None
    max_seq_length: Optional[int] = None
    # text=clip
    arch: Optional[str] = None
    weights: Optional[str] = None
    hf_repo: Optional[str] = None
    hf_cache_dir: Optional[str] = None
    quick_gelu: Optional[bool] = None
    normalize: Optional[bool] = None
    allow_random_init: Optional[bool] = None
    random_init_seed: Optional[int] = None


@dataclass
class PartTexts:
    backend: str = MISSING
    parts: List[str] = MISSING              # part texts per caption (arms, legs)
    prompt_version: str = MISSING
    no_movement_text: str = MISSING
    index_path: str = MISSING
    out_dir: str = MISSING
    cache_path: str = MISSING
    retry_fallbacks: bool = MISSING
    max_fallback_rate: float = MISSING
    concurrency: int = MISSING
    # part_texts=openai
    base_url: Optional[str] = None
    model: Optional[str] = None
    api_key_env: Optional[str] = None
    temperature: Optional[float] = None
    allow_insecure_http: Optional[bool] = None   # plain http to a non-loopback host
    max_tokens: Optional[int] = None
    timeout_s: Optional[float] = None
    max_retries: Optional[int] = None
    backoff_base_s: Optional[float] = None
    backoff_max_s: Optional[float] = None
    backoff_jitter: Optional[float] = None
    retry_after_max_s: Optional[float] = None
    max_format_attempts: Optional[int] = None
    allow_extra_lines: Optional[bool] = None
    request_failure: Optional[str] = None
    max_consecutive_failures: Optional[int] = None
    seed: Optional[int] = None


@dataclass
class InteractionSubset:
    n_interactive: Optional[int] = _COUNT()
    n_non_interactive: Optional[int] = _SOME()
    non_interactive_ratio: float = _range(0)
    mirror: str = _choice("exclude", "keep")


@dataclass
class Interactions:                     # party.text.interactions (SPEC-textim §3)
    backend: str = _choice("rules", "openai", "oracle")
    generate_backend: Optional[str] = MISSING
    model: str = MISSING
    base_url: str = MISSING
    api_key_env: str = MISSING
    allow_insecure_http: bool = MISSING
    prompt_version: str = MISSING
    temperature: float = _range(0)
    max_attempts: int = _COUNT()
    unsided: str = _choice("both", "right")
    span_overlap: float = _range(0, 1, above=True)
    max_fallback_rate: float = _range(0, 1)
    concurrency: int = _COUNT()
    cache_path: str = MISSING
    timeout_s: float = _POSITIVE()
    max_tokens: int = _COUNT()
    max_retries: int = _SOME()
    backoff_base_s: float = MISSING
    backoff_max_s: float = MISSING
    backoff_jitter: float = MISSING
    retry_after_max_s: float = MISSING
    max_consecutive_failures: int = _SOME()
    seed: int = MISSING
    oracle_root: Optional[str] = MISSING
    index_path: str = MISSING
    out_dir: str = MISSING
    subset: InteractionSubset = _group(InteractionSubset)


# --------------------------------------------------------------------------- vqvae

@dataclass
class LTE:
    enabled: bool = MISSING
    hidden: int = MISSING
    layers: int = MISSING
    per_position: bool = MISSING


@dataclass
class GTE:
    enabled: bool = MISSING
    hidden: int = MISSING
    layers: int = MISSING
    adjacency: str = MISSING
    residual: bool = MISSING


@dataclass
class Quantizer:
    decay: float = MISSING
    reset_threshold: float = MISSING


@dataclass
class VQModel:
    family: str = MISSING                   # temporal_vq | vq | rvq | a dotted model-class path
    window: int = MISSING
    codebook_size: int = MISSING
    code_dim: int = MISSING
    width: int = MISSING
    depth: int = MISSING
    dilation_growth: int = MISSING
    tail: str = MISSING
    baseline_pool: str = MISSING
    representation: str = _choice("h3d", "no_rot", "no_rot_no_vel")   # party.motion.features.REPRESENTATIONS
    lte: LTE = _group(LTE)
    gte: GTE = _group(GTE)
    quantizer: Quantizer = _group(Quantizer)


@dataclass
class VQLoss:
    rec_positions: str = MISSING
    lambda_rec: float = MISSING
    lambda_app: float = MISSING
    lambda_feat: float = MISSING
    lambda_vel: float = MISSING
    feat_loss: str = MISSING


@dataclass
class SideChecks:
    wave_margin: float = MISSING
    kick_lift_m: float = MISSING


@dataclass
class VQDiagnostics:
    max_baseline_ratio: float = MISSING
    min_code_spread: float = MISSING
    on_collapse: str = MISSING
    code_run_length: int = MISSING
    side_checks: SideChecks = _group(SideChecks)


@dataclass
class VQOptim:
    lr: float = _POSITIVE()
    lr_after: float = _SOME()
    milestone: int = _SOME()
    betas: List[float] = MISSING
    weight_decay: float = _SOME()
    warmup_steps: int = _SOME()
    grad_clip: float = _SOME()


@dataclass
class VQTrain:                               # _off_step: not in the resume key
    max_steps: int = _off_step(_COUNT())
    batch_size: int = _COUNT()
    crop: int = _COUNT()
    val_every: int = _off_step(_COUNT())
    ckpt_every: int = _off_step(field(default=MISSING))
    resume: bool = _off_step(field(default=MISSING))
    threads: Optional[int] = _off_step(_COUNT())
    render_samples: int = _off_step(_SOME())
    log_checkpoint: bool = _off_step(field(default=MISSING))


@dataclass
class VQMetrics:
    unit_scale: float = MISSING
    groups: Optional[str] = None            # a table of dataset.parts.groups: errors per group too


@dataclass
class VQEval:
    split: str = MISSING
    max_clips: Optional[int] = MISSING
    batch_size: int = MISSING


@dataclass
class StageTrainer:                          # vqvae.trainer, generator.trainer: trainer.* for one group
    precision: Optional[str] = MISSING   # null: trainer.precision; auto: bf16-mixed where native


@dataclass
class VQAblation:
    sweep: str = MISSING
    out_dir: str = MISSING
    fid: bool = MISSING
    fid_replications: int = MISSING


def _override_of(cls, name: str, extra: tuple = ()):
    """``cls`` with every key optional (``None`` = not overridden), nested groups likewise."""
    hints = typing.get_type_hints(cls)
    fields = []
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t):
            t = _override_of(t, f"{t.__name__}Override")
        fields.append((f.name, Optional[t], field(default=None, metadata=f.metadata)))
    out = dataclasses.make_dataclass(name, fields + list(extra))
    out.__module__ = __name__
    return out


#: ``vqvae.tokenizers.<stream>``: any ``vqvae.model`` key for one stream, plus an
#: optional ``train`` block overriding ``vqvae.train`` (party.tokenizers.config.stream_config)
VQTrainOverride = _override_of(VQTrain, "VQTrainOverride")
TokenizerOverride = _override_of(VQModel, "TokenizerOverride",
                                 (("train", Optional[VQTrainOverride], field(default=None)),))


@dataclass
class RVQ:                                  # family rvq (party.tokenizers.rvq)
    levels: int = _COUNT()
    quantizer_dropout: float = _SOME()


@dataclass
class H2VQRates:
    coarse: int = _COUNT()
    fine: int = _COUNT()


@dataclass
class H2VQ:                                 # family h2vq (party.methods.humantomato.h2vq)
    groups: str = MISSING                   # a table of dataset.parts.groups
    table: Dict[str, ChannelGroup] = MISSING   # that table (interpolated)
    fine: str = MISSING                     # the group quantized first
    rates: H2VQRates = _group(H2VQRates)
    transform: str = MISSING
    fusion_kernel: int = _COUNT()


@dataclass
class VQFamilies:                           # vqvae.families.<family>: joins the model config of that family's streams
    rvq: RVQ = _group(RVQ)
    h2vq: H2VQ = _group(H2VQ)


@dataclass
class Vqvae:
    stream: str = MISSING
    streams: List[str] = MISSING
    part_streams: List[str] = MISSING
    extra_streams: List[str] = field(default_factory=list)   # tokenizers under a stream alias (other families')
    out_dir: str = MISSING
    tokens_dir: str = MISSING
    resume_dir: str = MISSING
    model: VQModel = _group(VQModel)
    families: VQFamilies = _group(VQFamilies)
    tokenizers: Dict[str, TokenizerOverride] = MISSING   # type: ignore[valid-type]
    loss: VQLoss = _group(VQLoss)
    diagnostics: VQDiagnostics = _group(VQDiagnostics)
    optim: VQOptim = _group(VQOptim)
    train: VQTrain = _group(VQTrain)
    metrics: VQMetrics = _group(VQMetrics)
    eval: VQEval = _group(VQEval)
    trainer: StageTrainer = _group(StageTrainer)
    ablation: VQAblation = _group(VQAblation)


# --------------------------------------------------------------------------- evaluator

@dataclass
class EvaluatorWidths:
    word_size: int = MISSING
    pos_size: int = MISSING
    text_hidden: int = MISSING
    coemb: int = MISSING
    movement_hidden: int = MISSING
    movement_latent: int = MISSING
    motion_hidden: int = MISSING


@dataclass
class EvaluatorModel(EvaluatorWidths):
    dropout: float = MISSING


@dataclass
class MovementPretrain:
    enabled: bool = MISSING
    window: int = _COUNT()
    batch_size: int = _COUNT()
    lr: float = _POSITIVE()
    lambda_sparsity: float = MISSING
    lambda_smooth: float = MISSING
    max_steps: int = MISSING
    max_epochs: int = MISSING
    val_every_n_epochs: int = MISSING


@dataclass
class EvaluatorTrain:
    batch_size: int = _COUNT()
    lr: float = _POSITIVE()
    lr_after: Optional[float] = MISSING
    milestone: Optional[int] = MISSING
    negative_margin: float = MISSING
    grad_clip: float = _SOME()
    max_steps: int = MISSING
    max_epochs: int = MISSING
    val_every_n_epochs: int = MISSING


@dataclass
class EvaluatorTrainer:
    precision: str = MISSING
    num_workers: int = _SOME()


@dataclass
class EvaluatorReference:
    checkpoint: Optional[str] = MISSING
    glove_dir: Optional[str] = MISSING
    mean: Optional[str] = MISSING
    std: Optional[str] = MISSING
    model: EvaluatorWidths = _group(EvaluatorWidths)


@dataclass
class Evaluator:
    kind: str = MISSING
    stream: str = MISSING
    streams: List[str] = MISSING
    out_dir: str = MISSING
    val_split: str = MISSING
    test_split: str = MISSING
    text_input: str = MISSING
    text_precision: str = MISSING
    glove_dir: Optional[str] = MISSING
    max_text_tokens: Optional[int] = MISSING
    max_text_len: int = MISSING
    max_motion_len: int = MISSING
    unit_length: int = MISSING
    drop_contacts: bool = MISSING
    model: EvaluatorModel = _group(EvaluatorModel)
    movement_pretrain: MovementPretrain = _group(MovementPretrain)
    freeze_movement: bool = MISSING
    train: EvaluatorTrain = _group(EvaluatorTrain)
    trainer: EvaluatorTrainer = _group(EvaluatorTrainer)
    reference: EvaluatorReference = _group(EvaluatorReference)


# --------------------------------------------------------------------------- eval

@dataclass
class Multimodality:
    replications: int = _COUNT()
    num_texts: int = _COUNT()
    times: int = _COUNT()


@dataclass
class EvalReport:
    clips: int = MISSING
    max_frames: int = MISSING


@dataclass
class EvalSources:
    ground_truth: bool = MISSING
    tokenizers: List[str] = MISSING
    tokenizers_dir: str = MISSING
    tokenizer_ckpt: Optional[str] = MISSING
    memo_reconstructions: bool = MISSING
    generated: Any = _union(str, List[str])  # auto | [run folders]
    generated_dir: str = MISSING


@dataclass
class Coherence:
    enabled: bool = MISSING
    sigma: float = MISSING
    kappa: float = MISSING
    window: int = MISSING
    stride: Optional[int] = MISSING
    tau_max: int = MISSING
    eps: float = MISSING
    beta_d: float = MISSING
    beta_theta: float = MISSING
    end_joints: Optional[Dict[str, int]] = MISSING
    reference_split: str = MISSING
    reference_max_clips: Optional[int] = MISSING


@dataclass
class Physics:                              # eval.physics: party.evaluation.physics
    enabled: bool = MISSING
    length_unit: float = _POSITIVE()        # metres per joint-position unit
    contact_height: float = _POSITIVE()
    skate_speed: float = _range(0)
    skate_window: int = _COUNT()
    float_tol: float = _range(0)
    flight_g: float = _POSITIVE()


@dataclass
class EvalInteraction:                      # eval.interaction: party.evaluation.interaction (TextIM's metrics)
    enabled: bool = MISSING
    dir: str = MISSING
    hand_joints: List[int] = MISSING        # [left, right]
    foot_joints: List[int] = MISSING        # [left, right]
    foot_with_ankles: bool = MISSING
    boundary_joints: List[int] = MISSING    # where the parts meet: boundary speed
    seam_bones: List[List[int]] = MISSING   # [parent, child] bones joining two parts: seam bone error
    pos_unit: str = _choice("m", "cm", "mm")
    vel_unit: str = _choice("cm_per_frame", "m_per_frame", "mm_per_frame", "m_per_s")


@dataclass
class Efficiency:
    ait_samples: int = MISSING
    ait_warmup: int = MISSING


@dataclass
class SigmaKappaGrid:
    sigma: List[float] = MISSING
    kappa: List[float] = MISSING


@dataclass
class WindowTauGrid:
    window: List[int] = MISSING
    tau_max: List[int] = MISSING


@dataclass
class Calibrate:
    out_dir: str = MISSING
    split: str = MISSING
    max_clips: Optional[int] = MISSING
    min_shift: int = MISSING
    mix_mode: str = MISSING
    freeze_part: str = MISSING
    criterion: str = MISSING
    sigma_kappa: SigmaKappaGrid = _group(SigmaKappaGrid)
    window_tau: WindowTauGrid = _group(WindowTauGrid)
    beta: List[float] = MISSING


@dataclass
class Eval:
    out_dir: str = MISSING
    metrics_dir: str = MISSING
    metrics_digits: int = MISSING
    split: str = MISSING
    seed: int = MISSING
    replications: int = _COUNT()
    batch_size: int = _COUNT()
    large_batch_size: int = _COUNT()
    top_k: int = _COUNT()
    diversity_times: int = _COUNT()
    embed_batch_size: int = _COUNT()
    max_motion_len: int = MISSING
    unit_length: int = _COUNT()
    device: str = MISSING
    workers: Optional[int] = _COUNT()
    ci_z: float = _POSITIVE()
    multimodality: Multimodality = _group(Multimodality)
    mpjpe_scale: float = MISSING
    retrievers: Dict[str, str] = MISSING     # name -> folder (party.evaluation.retrievers)
    sources: EvalSources = _group(EvalSources)
    coherence: Coherence = _group(Coherence)
    physics: Physics = _group(Physics)
    interaction: EvalInteraction = _group(EvalInteraction)
    efficiency: Efficiency = _group(Efficiency)
    calibrate: Calibrate = _group(Calibrate)
    held_out_subset: bool = MISSING
    report: EvalReport = _group(EvalReport)


# --------------------------------------------------------------------------- generator

@dataclass
class GenModel:
    dim: int = _COUNT()
    part_layers: int = _COUNT()
    holistic_layers: int = _COUNT()
    heads: int = _COUNT()
    mlp_ratio: int = _COUNT()
    dropout: float = _range(0, 1, below=True)
    max_tokens: int = _range(2)
    ptg_k: int = _COUNT()
    ptg_hidden: int = _COUNT()
    pg_window: int = _COUNT()
    pg_lookahead: int = _range(0)
    pg_align: str = _choice("overlap", "generated")
    pg_hidden: int = _COUNT()
    hpf_heads: int = _COUNT()
    hpf_head_dim: int = _COUNT()
    text_norm: str = _choice("none", "standardize")
    cond_drop: float = _range(0, 1, below=True)
    null_condition: str = _choice("whole_body", "text")
    part_embed: str = _choice("shared", "detached", "separate")
    ptg_init: str = _choice("he", "normal")


@dataclass
class GenLoss:
    lambda_div: float = _SOME()
    tau: float = _POSITIVE()
    lambda_aux: float = _SOME()
    no_movement_text: str = MISSING


@dataclass
class GenCorruption:
    enabled: bool = MISSING
    prob: float = _PROB()
    part_context_prob: float = _PROB()


@dataclass
class GenOptim:
    lr: float = _POSITIVE()
    lr_after: float = _SOME()
    milestone: int = _SOME()
    betas: List[float] = MISSING
    weight_decay: float = _SOME()
    grad_clip: float = _SOME()


@dataclass
class GenTrain:                              # _off_step: not in the resume key
    batch_size: int = _COUNT()
    bucket_pool: int = _SOME()         # 0: uniform random batches; N: length-bucketed within pools of N batches
    val_split: str = MISSING
    max_steps: int = _off_step(_COUNT())
    val_every: int = _off_step(_COUNT())
    ckpt_every: int = _off_step(field(default=MISSING))
    resume: bool = _off_step(field(default=MISSING))
    num_workers: int = _off_step(_SOME())
    threads: Optional[int] = _off_step(_COUNT())
    log_checkpoint: bool = _off_step(field(default=MISSING))
    render_samples: int = _off_step(_SOME())
    render_max_frames: int = _off_step(field(default=MISSING))
    prompts: List[str] = _off_step(field(default=MISSING))
    untrained_loss_ratio: float = _off_step(field(default=MISSING))
    on_untrained: str = _off_step(_choice("error", "warn"))


@dataclass
class GenAblation:
    sweep: str = MISSING
    out_dir: str = MISSING
    replications: int = _COUNT()


@dataclass
class GenGenerate:
    split: str = MISSING
    repeats: int = _COUNT()
    batch_size: int = _COUNT()
    sampling: str = _choice("greedy", "sample")
    temperature: float = _POSITIVE()
    top_k: Optional[int] = _COUNT()
    top_p: Optional[float] = _range(0, 1, above=True)
    seed: int = MISSING
    use_cache: bool = MISSING
    cond_scale: float = _SOME()             # classifier-free guidance (1 = off)
    part_cond_scale: Optional[float] = _SOME()   # the Arms / Legs streams' scale (null: cond_scale)
    lengths: str = _choice("gt", "free")    # gt: the clips' token counts | free
    min_frames: Optional[int] = _COUNT()     # free length: no END before this many frames
    # read only when generating for people's texts (party.pipeline_params: not params of the
    # pipeline's generate stage)
    texts: Optional[List[str]] = _people_only(field(default=MISSING))
    texts_file: Optional[str] = _people_only(field(default=MISSING))
    frames: Optional[List[int]] = _people_only(field(default=MISSING))
    run: Optional[str] = _people_only(field(default=MISSING))
    out: str = _people_only(field(default=MISSING))
    formats: List[str] = _people_only(field(default=MISSING))
    log_artifacts: str = _people_only(_choice("previews", "all", "none"))   # files logged into the run
    previews: int = _people_only(_SOME())   # log_artifacts=previews: the GIF / MP4 of this many texts


@dataclass
class GenRegistry:
    name: str = MISSING


@dataclass
class Generator:
    method: str = MISSING
    # each entry: the Config of the family its `family` key names (party.methods); typed Any for
    # OmegaConf, checked as MethodEntry
    methods: Dict[str, Any] = field(default=MISSING, metadata={"entry": MethodEntry})
    plugins: List[str] = MISSING                 # modules registering more method families
    streams: List[str] = MISSING
    tokens_dir: str = MISSING
    tokenizers_dir: str = MISSING
    out_dir: str = MISSING
    resume_dir: str = MISSING
    generated_dir: str = MISSING
    allow_mismatch: bool = MISSING           # use inputs other than a model's recorded ones (party.provenance)
    model: GenModel = _group(GenModel)
    loss: GenLoss = _group(GenLoss)
    corruption: GenCorruption = _group(GenCorruption)
    optim: GenOptim = _group(GenOptim)
    train: GenTrain = _group(GenTrain)
    trainer: StageTrainer = _group(StageTrainer)
    generate: GenGenerate = _group(GenGenerate)
    registry: GenRegistry = _group(GenRegistry)
    ablation: GenAblation = _group(GenAblation)


# --------------------------------------------------------------------------- root

@dataclass
class Repro:                                 # `party repro -j N`
    expected_seconds: Dict[str, float] = MISSING   # stage or template (train_vqvae) -> wall time, until logs/repro/summary.json has one
    fork_server: bool = MISSING                    # stages fork from one warm interpreter (party.forkserver)


@dataclass
class Preemption:
    requeue: bool = MISSING                  # party.training.RequeueOnSignal (SLURM jobs)
    signal: str = _choice("USR1", "USR2")


@dataclass
class TMAModel:
    latent_dim: int = _COUNT()
    layers: int = _COUNT()
    heads: int = _COUNT()
    ff: int = _COUNT()
    dropout: float = _SOME()
    vae: bool = MISSING


@dataclass
class TMALoss:
    lambda_kl: float = _SOME()
    lambda_e: float = _SOME()
    lambda_nce: float = _SOME()
    tau: float = _POSITIVE()
    filter_threshold: float = MISSING


@dataclass
class TMAOptim:
    lr: float = _POSITIVE()
    betas: List[float] = MISSING
    weight_decay: float = _SOME()


@dataclass
class TMATrain:
    batch_size: int = _COUNT()
    max_steps: int = _COUNT()
    val_every: int = _COUNT()
    max_len: int = _COUNT()
    unit_len: int = _COUNT()
    threads: Optional[int] = _COUNT()


@dataclass
class TMAEval:
    ks: List[int] = MISSING
    set_sizes: Dict[str, int] = MISSING
    b_threshold: float = MISSING
    seed: int = MISSING


@dataclass
class Tma:                                   # conf/tma (party.methods.humantomato.tma_train)
    which: str = MISSING
    eval_model: str = MISSING
    models: Dict[str, int] = MISSING
    out_dir: str = MISSING
    text_backbone: str = MISSING
    max_text_tokens: int = _COUNT()
    model: TMAModel = _group(TMAModel)
    loss: TMALoss = _group(TMALoss)
    optim: TMAOptim = _group(TMAOptim)
    train: TMATrain = _group(TMATrain)
    eval: TMAEval = _group(TMAEval)
    trainer: StageTrainer = _group(StageTrainer)


@dataclass
class Config:
    seed: int = MISSING
    progress: bool = MISSING
    objective: Optional[str] = MISSING      # the metric a stage's Hydra app returns (null: all)
    paths: Paths = _group(Paths)
    dataset: Dataset = _group(Dataset)
    tracking: Tracking = _group(Tracking)
    trainer: Trainer = _group(Trainer)
    text: Text = _group(Text)
    part_texts: PartTexts = _group(PartTexts)
    interactions: Interactions = _group(Interactions)
    vqvae: Vqvae = _group(Vqvae)
    evaluator: Evaluator = _group(Evaluator)
    tma: Tma = _group(Tma)
    eval: Eval = _group(Eval)
    generator: Generator = _group(Generator)
    repro: Repro = _group(Repro)
    preemption: Preemption = _group(Preemption)


#: the config groups of conf/ and their schema
SCHEMA_GROUPS: dict[str, type] = {"dataset": Dataset, "tracking": Tracking, "trainer": Trainer,
                                  "text": Text, "part_texts": PartTexts, "interactions": Interactions,
                                  "vqvae": Vqvae,
                                  "evaluator": Evaluator, "tma": Tma, "eval": Eval, "generator": Generator}


# --------------------------------------------------------------------------- validation

_NONE = type(None)


def _unoptional(t) -> tuple[Any, bool]:
    if typing.get_origin(t) is typing.Union:
        args = [a for a in typing.get_args(t) if a is not _NONE]
        if len(args) < len(typing.get_args(t)):
            return (args[0] if len(args) == 1 else typing.Union[tuple(args)]), True
    return t, False


def _noun(t) -> str:
    t, optional = _unoptional(t)
    origin = typing.get_origin(t)
    if origin in (list, List):
        s = f"list of {_noun(typing.get_args(t)[0])}"
    elif origin is Literal:
        s = "one of " + ", ".join(map(str, typing.get_args(t)))
    elif origin in (dict, Dict) or dataclasses.is_dataclass(t) or t is MethodEntry:
        s = "mapping"
    else:
        s = {bool: "bool", int: "int", float: "number", str: "string", Any: "value"}.get(t, str(t))
    return s + (" or null" if optional else "")


def _describe(t) -> str:
    s = _noun(t)
    if s.startswith("one of "):
        return s
    return ("an " if s[0] in "aeiou" else "a ") + s + (" (true/false)" if s == "bool" else "")


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def _join(prefix: str, key) -> str:
    return f"{prefix}[{key}]" if isinstance(key, int) else (f"{prefix}.{key}" if prefix else str(key))


def _is_missing(v) -> bool:
    return isinstance(v, str) and v == MISSING


def _fail(where: str, key: str, problem: str):
    raise ConfigError(f"{where}: {key}: {problem}", key)


def _matches(value, t) -> bool:
    """Whether ``value`` is of schema type ``t`` (strict: no str -> number, no int -> bool)."""
    if _is_missing(value):
        return True
    t, optional = _unoptional(t)
    if value is None:
        return optional
    origin = typing.get_origin(t)
    if t is Any:
        return True
    if t is bool:
        return isinstance(value, bool)
    if t is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if t is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if t is str:
        return not isinstance(value, (list, tuple, dict, Mapping))
    if origin is Literal:
        return any(value == a and type(value) is type(a) for a in typing.get_args(t))
    if origin is typing.Union:
        return any(_matches(value, a) for a in typing.get_args(t))
    if origin in (list, List):
        return isinstance(value, (list, tuple)) and all(_matches(v, typing.get_args(t)[0]) for v in value)
    if origin in (dict, Dict):
        return isinstance(value, Mapping) and all(_matches(v, typing.get_args(t)[1]) for v in value.values())
    return isinstance(value, Mapping)


@functools.lru_cache(maxsize=None)
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _check(t, value, key: str, where: str, partial: bool, union: tuple = (), bounds: tuple | None = None,
           entry: type | None = None) -> None:
    if _is_missing(value):
        return
    t, optional = _unoptional(t)
    if value is None:
        if not optional:
            _fail(where, key, f"null is not allowed (expected {_describe(t)})")
        return
    if union:
        if not any(_matches(value, u) for u in union):
            _fail(where, key, f"{_short(value)} is not " + " or ".join(_describe(u) for u in union))
        return
    origin = typing.get_origin(t)
    if t is MethodEntry:
        t = _family_config(value, key, where)
    if dataclasses.is_dataclass(t):
        if not isinstance(value, Mapping):
            _fail(where, key, f"{_short(value)} is not a mapping (a group of keys)")
        hints = _hints(t)
        names = list(hints)
        for k in value:
            if k not in hints:
                near = difflib.get_close_matches(str(k), names, n=1)
                hint = f"did you mean {_join(key, near[0])}?" if near else "typo?"
                raise ConfigError(f"{where}: unknown key {_join(key, k)} (not in the schema; {hint})",
                                  _join(key, k))
        for f in dataclasses.fields(t):
            sub = _join(key, f.name)
            if f.name in value:
                _check(hints[f.name], value[f.name], sub, where, partial, f.metadata.get("union", ()),
                       f.metadata.get("range"), f.metadata.get("entry"))
                choices = f.metadata.get("choices")
                if choices and not _is_missing(value[f.name]) and value[f.name] not in choices:
                    _fail(where, sub, f"{_short(value[f.name])} is not one of {', '.join(choices)}")
            elif not partial and f.default is not None:         # required (MISSING or a group)
                raise ConfigError(f"{where}: missing key {sub} (required by the schema)", sub)
    elif origin in (dict, Dict):
        if not isinstance(value, Mapping):
            _fail(where, key, f"{_short(value)} is not {_describe(t)}")
        vt = typing.get_args(t)[1]
        for k, v in value.items():
            if not isinstance(k, str):
                _fail(where, _join(key, k), f"key {k!r} is not a string")
            _check(entry or vt, v, _join(key, k), where, partial)
    elif origin in (list, List):
        if not isinstance(value, (list, tuple)):
            _fail(where, key, f"{_short(value)} is not {_describe(t)}")
        for i, v in enumerate(value):
            _check(typing.get_args(t)[0], v, _join(key, i), where, partial)
    elif not _matches(value, t):
        quoted = isinstance(value, str) and _matches(_yaml_scalar(value), t)
        _fail(where, key, f"{_short(value)} is not {_describe(t)}" + (" (a quoted string)" if quoted else ""))
    elif bounds is not None:
        lo, hi, above, below = bounds
        if lo is not None and (value <= lo if above else value < lo):
            _fail(where, key, f"{_short(value)} is out of range: must be {'>' if above else '>='} {lo}")
        if hi is not None and (value >= hi if below else value > hi):
            _fail(where, key, f"{_short(value)} is out of range: must be {'<' if below else '<='} {hi}")


def _family_config(value, key: str, where: str):
    """The ``Config`` dataclass of the method family ``value["family"]`` names."""
    from party import methods
    if not isinstance(value, Mapping):
        _fail(where, key, f"{_short(value)} is not a mapping (a method: family and its keys)")
    fam = value.get("family")
    if _is_missing(fam) or fam is None:
        raise ConfigError(f"{where}: missing key {_join(key, 'family')} (one of {', '.join(sorted(methods.families()))})",
                          _join(key, "family"))
    try:
        return methods.family(str(fam)).Config
    except KeyError as e:
        raise ConfigError(f"{where}: {_join(key, 'family')}: {e.args[0]}", _join(key, "family")) from None


def _yaml_scalar(s: str):
    import yaml
    try:
        return yaml.safe_load(s)
    except yaml.YAMLError:
        return s


def _is_data(x) -> bool:
    """Plain YAML data without interpolations: str-keyed dicts, lists, scalars, no ``${``."""
    if isinstance(x, dict):
        return all(isinstance(k, str) and _is_data(v) for k, v in x.items())
    if isinstance(x, list):
        return all(_is_data(v) for v in x)
    if isinstance(x, str):
        return "${" not in x
    return x is None or isinstance(x, (bool, int, float))


def _plain(cfg, where: str) -> dict:
    from party.secrets import defer_unset, scan
    if isinstance(cfg, dict) and _is_data(cfg):   # nothing to resolve: OmegaConf would return a copy
        return copy.deepcopy(cfg)
    try:
        node = cfg if isinstance(cfg, (DictConfig, ListConfig)) else OmegaConf.create(cfg)
        scan(node)                     # values read with oc.env are masked wherever they are logged
        raw, unset = defer_unset(OmegaConf.to_container(node, resolve=False))
        if unset:                      # only a read of such a value fails, naming the variable
            node = OmegaConf.create(raw)
        plain = OmegaConf.to_container(node, resolve=True)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", "") or ""
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ConfigError(f"{where}: {key + ': ' if key else ''}{msg}", key) from None
    if not isinstance(plain, dict):
        raise ConfigError(f"{where}: the config is not a mapping of keys (got {type(plain).__name__})")
    return plain


def validate(cfg, where: str = "config", *, partial: bool = False) -> DictConfig:
    """Check ``cfg`` (a DictConfig or a plain mapping, interpolations resolved first) against
    :class:`Config`; return it as a plain (non-struct) resolved DictConfig with the values as
    given. Raises :class:`ConfigError` (a ValueError) whose one-line message starts with
    ``where`` and names the dotted key. ``partial=True`` allows absent keys and groups
    (hand-built test configs); unknown keys and wrong types still fail."""
    plain = _plain(cfg, where)
    plugins = (plain.get("generator") or {}).get("plugins") if isinstance(plain.get("generator"), Mapping) else None
    if isinstance(plugins, (list, tuple)) and plugins:
        from party import methods
        try:
            methods.load_plugins([str(p) for p in plugins])
        except (ImportError, ValueError) as e:
            raise ConfigError(f"{where}: generator.plugins: {e}", "generator.plugins") from None
    _check(Config, plain, "", where, partial)
    _check_names(plain, where)
    _check_known(plain, where)
    return OmegaConf.create(plain)


# --------------------------------------------------------------------------- names

#: keys holding names (``party.names``): each becomes a folder or file name (``<out_dir>/<stream>/``,
#: ``<metrics_dir>/recon_<stream>.json``), and dvc.yaml pastes the streams (``${item}``) and the
#: methods (``${key}``) into the shell commands it runs. (dotted key, where its names are: the
#: value, its items, its keys, or the items of each of its values)
NAME_KEYS: tuple[tuple[str, str], ...] = (
    ("dataset.parts.streams", "items"), ("dataset.parts.parts", "keys"),
    ("dataset.parts.stream_parts", "keys"), ("dataset.parts.stream_parts", "value items"),
    ("dataset.parts.coherence", "keys"), ("dataset.parts.part_tokenizers", "items"),
    ("dataset.parts.aliases", "keys"), ("dataset.parts.group_streams", "keys"),
    ("vqvae.stream", "value"), ("vqvae.streams", "items"), ("vqvae.part_streams", "items"),
    ("vqvae.extra_streams", "items"), ("vqvae.tokenizers", "keys"),
    ("evaluator.stream", "value"), ("evaluator.streams", "items"), ("tma.which", "value"), ("tma.models", "keys"),
    ("eval.retrievers", "keys"),
    ("eval.sources.tokenizers", "items"),
    ("generator.method", "value"), ("generator.methods", "keys"), ("generator.streams", "items"),
)


def _check_names(plain: Mapping, where: str) -> None:
    """Every name under ``NAME_KEYS`` is a plain name; a ``ConfigError`` names the key otherwise
    (absent keys and ``???`` are left to the type checks)."""
    from party.names import NAME_RULE, is_name

    def bad(key: str, v, what: str = "") -> None:
        if not _is_missing(v) and not is_name(v):
            _fail(where, key, f"{what}{_short(v)} is not a plain name ({NAME_RULE})")

    for dotted, how in NAME_KEYS:
        node: Any = plain
        for k in dotted.split("."):
            node = node.get(k) if isinstance(node, Mapping) else None
        if node is None or _is_missing(node):
            continue
        if how == "value":
            bad(dotted, node)
        elif how == "items" and isinstance(node, (list, tuple)):
            for i, v in enumerate(node):
                bad(_join(dotted, i), v)
        elif how == "keys" and isinstance(node, Mapping):
            for k in node:
                bad(dotted, k, "key ")
        elif how == "value items" and isinstance(node, Mapping):
            for k, items in node.items():
                for i, v in enumerate(items if isinstance(items, (list, tuple)) else ()):
                    bad(_join(_join(dotted, k), i), v)


# --------------------------------------------------------------------------- known choices

#: ``evaluator.kind``: trained (``<evaluator.out_dir>/<stream>/finest.tar``) | reference (the published
#: T2M checkpoint; ``party.evaluation.loading.load_evaluators``)
EVALUATOR_KINDS = ("trained", "reference")


def _check_known(plain: Mapping, where: str) -> None:
    """Every key that picks a registered thing picks a known one, so composing refuses what no stage
    can run: ``generator.method`` is a key of ``generator.methods`` (each entry's ``family`` is a
    registered method family: checked with the entry's schema), ``vqvae.model.family`` and each
    ``vqvae.tokenizers.<stream>.family`` a registered tokenizer family or an importable model class
    (``party.tokenizers.vqvae.family_class``), ``evaluator.kind`` one of ``EVALUATOR_KINDS``. A
    ``ConfigError`` names the key and lists the known ones (absent keys and ``???`` are left alone)."""
    def at(dotted: str):
        node: Any = plain
        for k in dotted.split("."):
            node = node.get(k) if isinstance(node, Mapping) else None
        return None if _is_missing(node) else node

    method, methods = at("generator.method"), at("generator.methods")
    if method is not None and isinstance(methods, Mapping) and method not in methods:
        _fail(where, "generator.method", f"{_short(method)} is not a method of generator.methods "
                                         f"(known: {', '.join(map(str, methods))})")
    families = {"vqvae.model.family": at("vqvae.model.family")}
    tokenizers = at("vqvae.tokenizers")
    for stream, over in (tokenizers.items() if isinstance(tokenizers, Mapping) else ()):
        if isinstance(over, Mapping):
            families[f"vqvae.tokenizers.{stream}.family"] = at(f"vqvae.tokenizers.{stream}.family")
    for key, fam in families.items():
        if fam is not None:
            from party.tokenizers.vqvae import family_class
            try:
                family_class(str(fam))
            except (KeyError, TypeError) as e:
                _fail(where, key, " ".join(str(e.args[0]).split()))       # one line (an import error has several)
    kind = at("evaluator.kind")
    if kind is not None and kind not in EVALUATOR_KINDS:
        _fail(where, "evaluator.kind", f"{_short(kind)} is not a known evaluator kind "
                                       f"(known: {', '.join(EVALUATOR_KINDS)})")
