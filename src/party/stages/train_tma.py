"""``party train_tma tma.which=<prior|eval>``: train one TMA text-motion model (HumanTOMATO's).

Reads ``tma.*`` (sizes, losses, budget, the seed of each model in ``tma.models``), ``text.*``
(the token features it reads), the prepared dataset; writes ``<tma.out_dir>/<which>/`` atomically:
``model.pt``, ``metrics.json`` (test-split ground-truth retrieval, protocols A-D both ways, beside
the untrained network and chance), ``config.yaml``. ``tma.models`` holds ``prior`` (the generator's
alignment loss) and ``eval`` (the evaluator), trained with different seeds; ``tma.eval_model``
names the one that scores (``eval.retrievers.tma``): ``eval`` by default, ``prior`` as the paper does.
"""
from __future__ import annotations

from pathlib import Path

from party.stage import stage


@stage("train_tma", run_name=lambda cfg: f"train_tma-{cfg.tma.which}", tags=lambda cfg: {"party.tma": cfg.tma.which})
def run(cfg, run_) -> dict:
    from party.methods.humantomato.tma_train import train_tma

    return train_tma(cfg, str(cfg.tma.which), Path(cfg.tma.out_dir) / str(cfg.tma.which), run_)
