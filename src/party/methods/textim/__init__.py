"""TextIM: part-aware interactive motion synthesis from text (a platform method family)."""
