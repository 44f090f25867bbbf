"""Stage-2 generator: ParTY's Part-Guided Network (PTG, part/holistic transformers, PG, HPF) and the
holistic-only / part-wise baselines. ``schedule`` holds the part-then-holistic cycle alignment."""
from party.generator.kv_cache import KVCache
from party.generator.model import GeneratorSpec, PartyGenerator

__all__ = ["GeneratorSpec", "KVCache", "PartyGenerator"]
