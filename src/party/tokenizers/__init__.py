"""Temporal-aware VQ-VAE tokenizers (SPEC §1): holistic, Arms and Legs from one code path.

    from party.tokenizers import load_tokenizer, TokenStore
    tok = load_tokenizer("data/tokenizers/holistic")        # model.pt, folder or last.ckpt
    codes = TokenStore.open("data/tokens/holistic").get("000021")
    feats = tok.detokenize(codes)                            # raw (n*w, D) features

The method family is ``vqvae.model.family`` (``temporal_vq``; ``vq`` and ``rvq``, the
convolutional VQ-VAE with one or ``rvq.levels`` residual codebooks; ``build_tokenizer``,
``register_family``); ``TokenizerProtocol`` (``party.tokenizers.protocol.Tokenizer``)
is what extraction and evaluation use of any family.
"""
from party.tokenizers.protocol import Codec, TokenizerModel
from party.tokenizers.protocol import Tokenizer as TokenizerProtocol
from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.temporal import GlobalTemporalEnhancement, LocalTemporalEnhancement
from party.tokenizers.tokens import TokenStore, write_token_store
from party.tokenizers.vqvae import (FAMILIES, VQVAE, Tokenizer, bits_per_frame, build_model, build_tokenizer,
                                    family_class, load_tokenizer, register_family, save_tokenizer)
from party.tokenizers import rvq  # noqa: E402,F401  (registers the families vq and rvq)

__all__ = ["EMAQuantizer", "GlobalTemporalEnhancement", "LocalTemporalEnhancement", "TokenStore",
           "write_token_store", "VQVAE", "Tokenizer", "load_tokenizer", "save_tokenizer",
           "FAMILIES", "bits_per_frame", "build_model", "build_tokenizer", "family_class", "register_family",
           "Codec", "TokenizerModel", "TokenizerProtocol"]
