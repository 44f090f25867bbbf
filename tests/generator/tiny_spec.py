"""The tiny generator spec the generator tests share (vocabularies, windows, dims, methods)."""
import torch

from party.methods.party.model import GeneratorSpec, PartyGenerator

VOCAB = {"holistic": 11, "arms": 7, "legs": 6}
WINDOWS = {"holistic": 8, "arms": 12, "legs": 12}
D_TEXT = 16
MODEL = dict(dim=32, part_layers=2, holistic_layers=2, heads=4, mlp_ratio=2, dropout=0.0, max_tokens=20,
             ptg_k=3, ptg_hidden=24, pg_window=3, pg_hidden=16, hpf_heads=2, hpf_head_dim=8, text_norm="none", cond_drop=0.0,
             ptg_init="he", pg_lookahead=3, pg_align="generated", null_condition="text",
             part_embed="shared")
LOSS = dict(lambda_div=0.1, tau=0.05, lambda_aux=0.1)
METHODS = {"party": dict(kind="party", pg=True, ptg=True, hpf=True, aux=True),
           "holistic": dict(kind="holistic", pg=False, ptg=False, hpf=False, aux=False),
           "partwise": dict(kind="partwise", pg=False, ptg=True, hpf=False, aux=True)}


def build(kind="party", seed=0, model=None, **switches) -> PartyGenerator:
    """A freshly seeded tiny model of ``kind`` (``model``: overrides of ``MODEL``)."""
    torch.manual_seed(seed)
    spec = GeneratorSpec.from_config({**MODEL, **(model or {})}, LOSS, {**METHODS[kind], **switches}, VOCAB,
                                     WINDOWS, D_TEXT)
    return PartyGenerator(spec)
