"""Text side: frozen text encoders, LLM part texts (Arms/Legs), stored embeddings.
See docs/text.md."""
from party.text.cache import PartTextCache, load_part_texts
from party.text.encoders import TextEncoder, build_text_encoder, text_encoder_id
from party.text.prompt import NO_MOVEMENT, is_no_movement, parse_answer
from party.text.store import EmbeddingCache, EmbeddingStore, text_key

__all__ = ["NO_MOVEMENT", "EmbeddingCache", "EmbeddingStore", "PartTextCache", "TextEncoder",
           "build_text_encoder", "is_no_movement", "load_part_texts", "parse_answer", "text_encoder_id",
           "text_key"]
