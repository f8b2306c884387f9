# fenics_elasto — every target bootstraps .venv (Python >= 3.12) on first use.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# The first interpreter >= 3.12 that actually runs (pyenv shims may exist but refuse).
PYTHON ?= $(shell for p in python3.13 python3.12 python3 $$(ls -d $$HOME/.pyenv/versions/3.1[2-9]*/bin/python3 /usr/bin/python3.1[2-9] 2>/dev/null); do \
  $$p -c 'import sys; sys.exit(sys.version_info < (3, 12))' >/dev/null 2>&1 && echo $$p && break; done)

.PHONY: docs-screenshots docs bench-adjoint demo demo-quick demo-accurate demo-prostate demo-prostate-quick test test-fast test-demo bench lint clean

$(STAMP): pyproject.toml constraints.txt
	@test -n "$(PYTHON)" || { echo "error: no python >= 3.12 found on PATH" >&2; exit 2; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[wheel,test]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) demos/prostate_elastography.py --out out/demo

demo-quick: $(STAMP)
	$(PY) demos/prostate_elastography.py --quick --out out/demo-quick

# The same story with the organ walls meshed 0.2 h instead of 0.35 h: E within ~1 %
# instead of ~4 %, at ~3x the time (see docs/validation.md).
demo-accurate: $(STAMP)
	$(PY) demos/prostate_elastography.py --organ-size 0.2 --out out/demo-accurate

# The real prostate surface (fenics_elasto/meshes/prostate) with a bladder and a rectum
# written by the demo: scene -> simulate -> image-like targets -> train --synthetic -> estimate.
demo-prostate: $(STAMP)
	$(PY) demos/real_prostate.py --out out/prostate

demo-prostate-quick: $(STAMP)
	$(PY) demos/real_prostate.py --quick --out out/prostate-quick

# On both cores (pytest-xdist; the slow tests first, so that none starts last); the
# DOLFINx JIT cache is shared by the workers (its compiles are locked per form). One
# BLAS thread per worker: two workers of two threads each would share two cores.
WORKERS = OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
test: $(STAMP)
	$(WORKERS) $(PY) -m pytest -q -n 2 --dist loadgroup --durations=15

test-fast: $(STAMP)
	$(WORKERS) $(PY) -m pytest -q -n 2 -m "not slow"

# The demos' own variants as tests (minutes each; not part of make test).
test-demo: $(STAMP)
	$(PY) -m pytest -q -m demo

bench: $(STAMP)
	$(PY) benchmarks/forward.py
	$(PY) benchmarks/gradient.py
	$(PY) benchmarks/reduced.py
	$(PY) benchmarks/convergence.py

# dolfinx-adjoint's taped gradient beside ours (benchmarks/gradient_taped.py), in a venv of
# its own that sees .venv's packages: --no-deps because it pins fenics-dolfinx, which
# dolfinx-solver-real provides under another name; the MPI library links let mpi4py load.
BENCH := .venv-bench
bench-adjoint: $(STAMP)
	test -x $(BENCH)/bin/python || $(PY) -m venv $(BENCH)
	$(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' > \
	  $$($(BENCH)/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/project-venv.pth
	for f in $(VENV)/lib/libmpi* $(VENV)/lib/mpich; do ln -sfn $(abspath $$f) $(BENCH)/lib/; done
	$(BENCH)/bin/python -m pip install -q --no-deps dolfinx-adjoint==0.4.0 fenicsx-compat==0.4.0
	$(BENCH)/bin/python -m pip install -q pyadjoint-ad h5py
	PYTHONPATH=$(CURDIR) $(BENCH)/bin/python benchmarks/gradient_taped.py

# ruff: pyflakes, pycodestyle, pyupgrade and bugbear checks; mypy over the package
# (both configured in pyproject.toml).
lint: $(STAMP)
	$(PY) -m ruff check fenics_elasto tests benchmarks demos docs
	$(PY) -m mypy fenics_elasto

clean:
	rm -rf $(VENV) $(BENCH) out .pytest_cache

# The docs site (docs/, Sphinx + MyST; docs/tooling.md says why) into docs/_build/html,
# warnings as errors. autodoc imports the package, so it builds in the project's venv.
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install -q -c constraints.txt -e '.[docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(PY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

# The front and API pages as a reader sees them, in Debian's chromium (apt-get install
# chromium; not needed by anything else): docs/_static/site/*.png.
CHROMIUM = chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
	--disable-background-networking --disable-component-update --disable-sync --hide-scrollbars --window-size=1280,1000
docs-screenshots: docs
	for page in index api; do $(CHROMIUM) --user-data-dir=$$(mktemp -d) \
		--screenshot=docs/_static/site/$$page.png file://$(CURDIR)/docs/_build/html/$$page.html; done
