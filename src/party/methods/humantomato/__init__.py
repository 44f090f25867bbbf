"""HumanTOMATO (Lu et al., ICML 2024) as a platform method family (``../shared/SPEC-humantomato.md``).

- ``h2vq``: the Holistic Hierarchical VQ-VAE tokenizer family (SPEC §2.2), registered as
  ``vqvae.model.family=h2vq`` when ``party.tokenizers`` looks the name up.
"""
