"""Synthetic faces with full ground truth: a 3D-aware procedural face, expression
controls, geometry-driven expression details, and a pinhole renderer. See docs/fixtures.md."""
