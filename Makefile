# Set-up and everyday commands. `make demo` and `make test` do everything on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
# Pinned; the build is the one your pip index serves (PyPI's Linux wheel brings CUDA). The CPU-only
# build: `make install TORCH="torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"`.
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: install demo test readme-pictures clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet $(TORCH)
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $@

demo: install
	$(BIN)/c4d demo

test: install
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# The README's pictures from the current demo (all of its first reconstructed val scene).
readme-pictures: install
	$(BIN)/c4d demo --out demo_out
	cp demo_out/pictures/readme/*.png docs/images/

clean:
	rm -rf $(VENV) build *.egg-info
