"""Temporal-aware VQ-VAE tokenizers (SPEC §1): holistic, Arms and Legs from one code path.

    from party.tokenizers import load_tokenizer, TokenStore
    tok = load_tokenizer("data/tokenizers/holistic")        # model.pt, folder or last.ckpt
    codes = TokenStore.open("data/tokens/holistic").get("000021")
    feats = tok.detokenize(codes)                            # raw (n*w, D) features
"""
from party.tokenizers.quantizer import EMAQuantizer
from party.tokenizers.temporal import GlobalTemporalEnhancement, LocalTemporalEnhancement
from party.tokenizers.tokens import TokenStore, write_token_store
from party.tokenizers.vqvae import VQVAE, Tokenizer, count_parameters, load_tokenizer, save_tokenizer

__all__ = ["EMAQuantizer", "GlobalTemporalEnhancement", "LocalTemporalEnhancement", "TokenStore",
           "write_token_store", "VQVAE", "Tokenizer", "count_parameters", "load_tokenizer", "save_tokenizer"]
