"""Part-text backends: ``build_backend(part_texts_cfg)`` -> object with ``name``, ``model``,
``fingerprint`` (prompt / rule-set hash) and ``describe(caption) -> PartTextResult``
(thread-safe)."""
from __future__ import annotations


def build_backend(cfg):
    name = cfg.get("backend")
    if name == "rules":
        from party.text.backends.rules import RulesBackend
        return RulesBackend(cfg)
    if name == "openai":
        from party.text.backends.openai import OpenAIBackend
        return OpenAIBackend(cfg)
    raise ValueError(f"part_texts.backend={name!r}: unknown backend (choose from ['openai', 'rules'])")
