"""The learned models of the book: ``qdt`` (the Quality-Diversity Transformer,
Chapter 4) and ``lenia`` (Flow Lenia and the Flow Lenia Transformer, Chapter 5)."""
