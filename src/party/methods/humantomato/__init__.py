"""HumanTOMATO (Lu et al., ICML 2024) as a platform method family (``../shared/SPEC-humantomato.md``).

- ``h2vq``: the Holistic Hierarchical VQ-VAE tokenizer family (SPEC §2.2), registered as
  ``vqvae.model.family=h2vq`` when ``party.tokenizers`` looks the name up.
- ``tma``: the TMA text-motion model (SPEC §3): ACTOR-style motion and text encoders, a motion
  decoder, the TEMOS losses with the filtered InfoNCE of App. D.1 (its training stage, the
  evaluator kind and the Hierarchical-GPT build on it).
"""
