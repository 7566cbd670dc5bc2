"""Research code beside the product: the synthetic-face and real-texture generators of the
fixtures and benchmarks, and the measurements and remedies of the synthesis benchmarks. It may
import ``stages`` and ``runner``; nothing in ``runner``, ``stages`` or ``editor`` imports it
(the import contracts in pyproject.toml, ``make lint``)."""
