# Two entry points (README): `make run` runs the default pipeline on the bundled fixture clip,
# `make test` runs the test suite. Both create the virtual environment on first use.
PY := .venv/bin/python
VENV_STAMP := .venv/.installed-$(shell sha256sum pyproject.toml | cut -c1-12)

.PHONY: run test browser egl bench fixtures clean

$(VENV_STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	# bytecode of the editable packages, as pip writes it for installed ones: start-up does not
	# recompile them where PYTHONDONTWRITEBYTECODE is set (stale files are recompiled by mtime)
	$(PY) -m compileall -q runner stages editor scripts > /dev/null
	rm -f .venv/.installed-* && touch $@

run: $(VENV_STAMP)
	.venv/bin/runner run pipeline.yaml --in fixtures/clips/calm.mp4 --out out

test: $(VENV_STAMP) browser egl
	$(PY) -m pytest -q tests

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
