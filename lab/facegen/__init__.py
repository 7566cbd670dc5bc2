"""The fixture generator's sequences and file writers; the face and its renderer are
:mod:`stages.eigen.facegen`. See docs/fixtures.md."""
