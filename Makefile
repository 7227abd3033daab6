# The two commands of the README: `make demo` runs the main job, `make test`
# runs the tests. Both create .venv and install what they need on first use.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean browser

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	@# uv installs what pip would (the same versions) in a third of the time; where it
	@# cannot (not on the index, or it reads no pip.conf: an index only pip knows), pip
	@# does. setuptools says on every editable install that a folder named like the
	@# package could shadow it (none does here: the roles install as bodynet.*)
	export PYTHONWARNINGS='ignore:Editable installation'; \
	  { $(BIN)/python -m pip install --quiet uv && \
	    $(BIN)/python -m uv pip install --quiet --python $(BIN)/python --compile-bytecode \
	      -e '.[dev,bench]'; } || $(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	@# the gateway's compiled kernels: built once here (seconds), cached beside their source
	$(BIN)/python -c 'import bodynet.gateway.kernels'
	@# our own modules' bytecode, as pip's for the libraries: where PYTHONDONTWRITEBYTECODE
	@# is set nothing else writes it, and every process would compile them again
	$(BIN)/python -m compileall -q bench cli clients core gateway kinematics nodes offline session
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/bodynet demo

# The game's page is tested in a real headless Chromium (driven by Playwright from
# PyPI, which cannot download its own browser here): Debian's chromium package,
# installed with apt-get when none is on the PATH and BODYNET_CHROMIUM is unset.
browser:
	@if [ -z "$$BODYNET_CHROMIUM" ] && ! command -v chromium >/dev/null 2>&1 \
	    && ! command -v chromium-browser >/dev/null 2>&1; then \
	  echo "installing Debian's chromium for the browser tests"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -q && \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; \
	fi

test: $(STAMP) browser
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -n 2 --dist loadgroup

bench: $(STAMP)
	$(BIN)/bodynet bench

clean:
	rm -rf $(VENV) bench-results .pytest_cache .mypy_cache .ruff_cache .hypothesis
