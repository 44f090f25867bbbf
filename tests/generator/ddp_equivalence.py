"""Train a tiny ParTY generator two steps and save its weights (run by test_ddp.py).

    python tests/generator/ddp_equivalence.py <devices> <global batch> <out.pt>

With ``devices`` = 2 the shared trainer builder runs Lightning DDP on two CPU processes (gloo),
each with half of the global batch (rank r takes items r, r + 2, ..., in order: the data module
below, so the comparison does not depend on the sampler's shuffling); with 1 device one process
takes the whole batch. Every sequence has the same lengths, no
dropout and no corruption, so the DDP-averaged gradient equals the one-process gradient and the
weights after two AdamW steps must agree.
"""
import sys
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader, Subset

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from generator.tiny_spec import D_TEXT, VOCAB, build  # noqa: E402

from party.config import compose  # noqa: E402
from party.generator.data import collate_generator  # noqa: E402
from party.generator.lit import GeneratorLit  # noqa: E402
from party.training import build_trainer  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PAD = {s: k + 1 for s, k in VOCAB.items()}


def items(n: int) -> list[dict]:
    g = torch.Generator().manual_seed(7)
    lengths = {"holistic": 9, "arms": 6, "legs": 6}
    return [{"text_emb": torch.randn(D_TEXT, generator=g),
             "part_emb": {p: torch.randn(D_TEXT, generator=g) for p in ("arms", "legs")},
             "no_movement": {"arms": bool(i % 3 == 0), "legs": False},
             "codes": {s: torch.randint(0, VOCAB[s], (n_s,), generator=g) for s, n_s in lengths.items()},
             "lengths": dict(lengths), "clip_id": f"c{i}", "caption": f"caption {i}"} for i in range(n)]


def main(devices: int, global_batch: int, out: str) -> None:
    cfg = compose(["trainer=cpu", f"trainer.devices={devices}", f"trainer.strategy={'ddp' if devices > 1 else 'auto'}",
                   "progress=false"], ROOT / "conf")
    model = build("party", seed=0, model={"dropout": 0.0})
    lit = GeneratorLit(model, {"lr": 1e-3, "lr_after": 1e-3, "milestone": 10, "betas": [0.5, 0.99],
                               "weight_decay": 0.0}, {"enabled": False, "prob": 0.0}, VOCAB, seed=0)
    data = items(4 * global_batch)

    class Data(L.LightningDataModule):
        def train_dataloader(self):
            rank, world = self.trainer.global_rank, self.trainer.world_size
            return DataLoader(Subset(data, range(rank, len(data), world)), batch_size=global_batch // world,
                              shuffle=False, collate_fn=lambda b: collate_generator(b, PAD))

    trainer = build_trainer(cfg, max_steps=2, limit_val_batches=0, default_root_dir=str(Path(out).parent),
                            use_distributed_sampler=False)
    trainer.fit(lit, datamodule=Data())
    if trainer.is_global_zero:
        torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, out)


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3])
