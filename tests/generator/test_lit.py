"""Training really trains in train mode: dropout and generator.model.cond_drop act during fit even when
the model was evaluated (eval mode) just before, as train_generator does for its untrained baseline.
(Lightning keeps each module's mode as it finds it at fit start.)"""
import lightning as L
from torch.utils.data import DataLoader

from party.generator.data import collate_generator
from party.generator.lit import GeneratorLit
from party.generator.train import _evaluate

from .ddp_equivalence import PAD, items
from .tiny_spec import VOCAB, build

OPTIM = {"lr": 1e-3, "lr_after": 1e-3, "milestone": 10, "betas": [0.5, 0.99], "weight_decay": 0.0}


def loader(n=8, batch=4):
    return DataLoader(items(n), batch_size=batch, shuffle=False, collate_fn=lambda b: collate_generator(b, PAD))


def test_evaluate_restores_the_mode():
    m = build("party", model={"dropout": 0.2})
    m.train()
    _evaluate(m, loader())
    assert m.training and all(x.training for x in m.modules())
    m.eval()
    _evaluate(m, loader())
    assert not m.training


def test_fit_trains_in_train_mode_after_an_evaluation():
    m = build("party", model={"dropout": 0.2, "cond_drop": 0.5})
    _evaluate(m, loader())               # the untrained baseline, as train_generator computes it
    m.eval()                             # even a model left in eval mode on purpose
    seen = []

    class Spy(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append(all(x.training for x in pl_module.model.modules()))

    lit = GeneratorLit(m, OPTIM, {"enabled": False, "prob": 0.0}, VOCAB, seed=0)
    trainer = L.Trainer(max_steps=2, accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
                        callbacks=[Spy()])
    trainer.fit(lit, loader())
    assert seen == [True, True]
