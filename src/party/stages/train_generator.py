"""``party train_generator generator.method=<party|holistic|partwise|...>``: train one generator.

Reads the token stores (``generator.tokens_dir``), the caption and part-text embeddings
(``text.embeddings_dir``, ``text.part_texts_path``) and ``generator.*``; writes
``<generator.out_dir>/<method>/`` (``model.pt``, ``last.ckpt``, ``config.json``,
``metrics.json``; see ``party.generator.train``), resuming from
``<generator.resume_dir>/<method>/<config hash>/`` after an interruption.
"""
from __future__ import annotations

from pathlib import Path

from party.generator.train import train_generator
from party.stage import stage


@stage("train_generator", run_name=lambda cfg: f"train_generator-{cfg.generator.method}",
       tags=lambda cfg: {"party.method": cfg.generator.method})
def run(cfg, run_) -> dict:
    method = str(cfg.generator.method)
    return train_generator(cfg, method, Path(cfg.generator.out_dir) / method, run_)
