"""The book's chapters, one module each (``qdnb.book.registry`` lists them): the
chapter's ``Config`` and its ``SCALES``, its ``METHODS``, the experiment that
produces its results, and the derived metrics and claim checks its notebook shows."""
