"""Shared machinery of the token-generating methods: the multi-stream token dataset
(``data``), the causal transformer and its KV cache (``layers``, ``kv_cache``), sampling
(``sampling``), the LightningModule that trains any model with ``losses(batch)`` (``lit``),
the training recipe (``train``), generated runs and people's files (``generate``, ``export``)
and registry packages (``package``). The methods themselves live in ``party.methods``."""
from party.generator.kv_cache import KVCache

__all__ = ["KVCache"]
