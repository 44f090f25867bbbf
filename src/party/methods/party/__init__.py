"""The ParTY family: ParTY (``kind: party``), its holistic-only baseline (``holistic``) and its parts-only
ablation (``partwise``), one model class (``model.PartyGenerator``) with the switches of
``config.PartyConfig``; trained by the token recipe (``party.generator.train``).

    generator:
      methods:
        party: {family: party, kind: party, pg: true, ptg: true, hpf: true, aux: true}
"""
from __future__ import annotations

from party.methods import register
from party.methods.party.config import PartyConfig
from party.methods.tokens import TokenMethod, TokenModelFamily

FORMAT = "party.generator/1"


class PartyMethod(TokenMethod):
    """A trained ParTY-family generator, ready to sample."""

    def index_fields(self, method_cfg) -> dict:
        spec = self.model.spec
        out = {"kind": spec.kind}
        if spec.kind == "party":                     # the ablation switches of Tab. 5
            out["switches"] = {k: bool(getattr(spec, k)) for k in ("pg", "ptg", "hpf")}
        return out


@register
class PartyFamily(TokenModelFamily):
    name = "party"
    Config = PartyConfig
    FORMAT = FORMAT

    @classmethod
    def build_model(cls, cfg, method: str, ds):
        from party.config import plain
        from party.methods import method_config
        from party.methods.party.model import GeneratorSpec, PartyGenerator
        g = cfg.generator
        spec = GeneratorSpec.from_config(plain(g.model), plain(g.loss), plain(method_config(g, method)),
                                         vocab=ds.codebook_sizes, windows=ds.windows, text_dim=ds.dim)
        model = PartyGenerator(spec)
        model.set_text_stats(ds.caption_embeddings)
        return model

    @classmethod
    def key_config(cls, cfg, method: str) -> dict:
        from party.config import plain
        from party.methods import method_config
        g = cfg.generator
        return {"model": plain(g.model), "loss": plain(g.loss),
                "method": {k: v for k, v in plain(method_config(g, method)).items() if k != "family"}}

    @classmethod
    def describe(cls, cfg, method: str) -> dict:
        from party.methods import method_config
        return {"kind": str(method_config(cfg.generator, method).kind)}

    @classmethod
    def wrap(cls, model, meta: dict) -> PartyMethod:
        return PartyMethod(model, meta, model.spec.streams, model.spec.max_tokens)

    @classmethod
    def model_from_spec(cls, spec: dict):
        from party.methods.party.model import GeneratorSpec, PartyGenerator
        spec.setdefault("cond_drop", 0.0)    # models saved before the key existed never saw the null condition
        spec.setdefault("ptg_init", "normal")  # ... and were built with N(0, 0.02) PTG MLPs (only matters at build)
        # ... and before Part Guidance's alignment, null condition and part embeddings were switches:
        # they ran the schedule T tokens ahead with PG over the tokens generated in the cycle, a null
        # condition of the text alone, and the part transformers' own token tables
        spec.setdefault("pg_lookahead", int(spec.get("pg_window", 3)))
        spec.setdefault("pg_align", "generated")
        spec.setdefault("null_condition", "text")
        spec.setdefault("part_embed", "shared")
        return PartyGenerator(GeneratorSpec(**spec))
