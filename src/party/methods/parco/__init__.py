"""The ParCo-like family (``family: parco``): a tokenizer per body part (``streams``: root, legs,
backbone, arms, each its own token store), a small GPT per part on the whole caption (no part
texts, no PTG), coordinated by sharing their features (``model.Coordination``), the six decoded
parts composed into one body (``PartLayout.merge``, joint 9's copies averaged). Trained by the
token recipe (``party.generator.train``) on its own streams.

    generator:
      methods:
        parco: {family: parco, streams: [root, right_leg, left_leg, backbone, right_arm, left_arm],
                dim: 256, layers: 4, heads: 8, coordinate: true, coord_layers: 3,
                coord_hidden: 512, end_stream: root}
"""
from __future__ import annotations

from party.methods import register
from party.methods.parco.config import ParcoConfig
from party.methods.tokens import TokenModelFamily

FORMAT = "party.generator/1+parco"


@register
class ParcoFamily(TokenModelFamily):
    name = "parco"
    Config = ParcoConfig
    FORMAT = FORMAT

    @classmethod
    def token_streams(cls, cfg, method: str) -> list[str]:
        from party.methods import method_config
        return [str(s) for s in method_config(cfg.generator, method).streams]

    @classmethod
    def build_model(cls, cfg, method: str, ds):
        from party.config import plain
        from party.methods import method_config
        from party.methods.parco.model import ParcoGenerator, ParcoSpec
        g = cfg.generator
        spec = ParcoSpec.from_config(plain(g.model), plain(method_config(g, method)), ds.codebook_sizes,
                                     ds.windows, ds.dim)
        model = ParcoGenerator(spec)
        model.set_text_stats(ds.caption_embeddings)
        return model

    @classmethod
    def key_config(cls, cfg, method: str) -> dict:
        from party.config import plain
        from party.methods import method_config
        g = cfg.generator
        model = plain(g.model)
        from party.methods.parco.model import SHARED_MODEL_KEYS
        return {"model": {k: model[k] for k in SHARED_MODEL_KEYS},
                "method": {k: v for k, v in plain(method_config(g, method)).items() if k != "family"}}

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        return {"kind": "parco" if bool(method_config(cfg.generator, method).coordinate) else "parco_independent"}

    @classmethod
    def model_from_spec(cls, spec: dict):
        from party.methods.parco.model import ParcoGenerator, ParcoSpec
        return ParcoGenerator(ParcoSpec(**spec))
