"""``party train_generator generator.method=<m>``: train one generator method of ``generator.methods``.

The method's family (``generator.methods.<m>.family``, ``party.methods``) trains it: the token
families read the token stores (``generator.tokens_dir``), the caption and part-text
embeddings (``text.embeddings_dir``, ``text.part_texts_path``) and ``generator.*``, and write
``<generator.out_dir>/<method>/`` (``method.json``, ``model.pt``, ``last.ckpt``, ``config.json``,
``metrics.json``; see ``party.generator.train``), resuming from
``<generator.resume_dir>/<method>/<config hash>/`` after an interruption. A generator whose
validation loss is not clearly below its untrained weights' (``generator.train.untrained_loss_ratio``)
fails the stage after its outputs are written (``generator.train.on_untrained: error``).
"""
from __future__ import annotations

from pathlib import Path

from party.stage import stage


@stage("train_generator", run_name=lambda cfg: f"train_generator-{cfg.generator.method}",
       tags=lambda cfg: {"party.method": cfg.generator.method})
def run(cfg, run_) -> dict:
    from party.methods import family_of
    method = str(cfg.generator.method)
    family = family_of(cfg.generator, method)        # the schema checked on_untrained's value
    out = Path(cfg.generator.out_dir) / method
    metrics = family.train(cfg, method, out, run_)
    if metrics.get("learned") is False and cfg.generator.train.on_untrained == "error":   # baselines: no key
        raise RuntimeError(f"{out}: generator has not learned: validation loss {metrics['final']['val/loss']:.3f} "
                           f"vs {metrics['untrained']['val/loss']:.3f} untrained (ratio above "
                           f"generator.train.untrained_loss_ratio {cfg.generator.train.untrained_loss_ratio}); "
                           "outputs and checkpoint kept; generator.train.on_untrained=warn to continue anyway")
    return metrics
