"""An empty module that ``tests/runner/test_import_ahead.py`` declares as a stage's import."""
