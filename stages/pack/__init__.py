"""An actor pack as data in the graph: ``pack.load`` and the bundles it outputs (docs/architecture.md, "Packs in the graph")."""
