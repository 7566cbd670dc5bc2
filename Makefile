# Two entry points (README): `make run` runs the default pipeline on the bundled fixture clip,
# `make test` runs the test suite. Both create the virtual environment on first use.
# `make test-fast` runs the tests not marked slow, browser, ray or subprocess (pyproject.toml);
# `make lint` runs ruff (lint and format check), mypy and import-linter (the packages' layers,
# pyproject.toml); `make bench` records benchmark areas.
PY := .venv/bin/python
VENV_STAMP := .venv/.installed-$(shell sha256sum pyproject.toml | cut -c1-12)

.PHONY: run test test-fast lint browser egl bench fixtures clean

$(VENV_STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	# bytecode of the editable packages, as pip writes it for installed ones: start-up does not
	# recompile them where PYTHONDONTWRITEBYTECODE is set (stale files are recompiled by mtime)
	$(PY) -m compileall -q runner stages editor lab scripts > /dev/null
	rm -f .venv/.installed-* && touch $@

run: $(VENV_STAMP)
	.venv/bin/runner run pipeline.yaml --in fixtures/clips/calm.mp4 --out out

test: $(VENV_STAMP) browser egl
	$(PY) -m pytest -q tests

test-fast: $(VENV_STAMP)
	$(PY) -m pytest -q -m "not slow and not browser and not ray and not subprocess" tests

lint: $(VENV_STAMP)
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .
	.venv/bin/mypy
	.venv/bin/lint-imports
	$(PY) scripts/benchmarks_page.py --check

# The benchmark areas of scripts/bench.py, each recorded to benchmarks/results/AREA.jsonl, then
# docs/benchmarks.md rendered from the records. The default leaves out the areas that run for a
# long time or need the dev clips (real, reenact, batch, shot, seen): `make bench AREAS="real shot"` records those.
AREAS ?= runner geometry propagation synthesis writers e2e landmarks smoothing editor eigen render3d photo_identity

bench: $(VENV_STAMP) browser egl
	set -e; for area in $(AREAS); do $(PY) scripts/bench.py $$area --json --record; done
	$(PY) scripts/benchmarks_page.py

# Debian's Chromium for the browser tests (editor, run report); a no-op once installed.
browser:
	bash .ci/install-browser

# Mesa's headless EGL for the 3D renderer (stages/render3d); a no-op once installed.
egl:
	bash .ci/install-egl

fixtures: $(VENV_STAMP)
	$(PY) scripts/make_fixtures.py --out fixtures

clean:
	rm -rf out .cache
