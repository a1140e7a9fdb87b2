# Set-up and everyday commands. `make demo` and `make test` do everything on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
# Pinned; the build is the one your pip index serves (PyPI's Linux wheel brings CUDA). The CPU-only
# build: `make install TORCH="torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"`.
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: install browser demo test readme-pictures clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet $(TORCH)
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $@

demo: install
	$(BIN)/c4d demo

# Headless Chromium for the browser tests (tests/test_view.py) and `c4d view --screenshot`: found
# on PATH, else installed from Debian's packages where this is root with apt-get; where neither
# works those tests are skipped and say why.
BROWSERS := chromium chromium-browser google-chrome google-chrome-stable
browser:
	@for b in $(BROWSERS); do command -v $$b >/dev/null 2>&1 && { echo "browser: $$(command -v $$b)"; exit 0; }; done; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		(apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium) >/dev/null \
			&& echo "browser: installed $$(command -v chromium)" && exit 0; \
	fi; \
	echo "browser: no Chromium found or installed (sudo apt-get install chromium); the browser tests will be skipped"

test: install browser
	$(BIN)/python -m pytest $(PYTEST_ARGS)

# The README's pictures from the current demo (all of its first reconstructed val scene, rendered
# again at the reconstruction's size by the recon-data step); the
# 4D view is drawn by `c4d view --screenshot` (headless Chromium, as the browser tests draw it).
DEMO_RECON := demo_out/reconstruct/scene-000/c4d
DEMO_TRUTH := demo_out/recon-data/movi-e
readme-pictures: install browser
	$(BIN)/c4d demo --out demo_out
	cp demo_out/pictures/readme/*.png docs/images/
	$(BIN)/c4d view $(DEMO_RECON) --gt $(DEMO_TRUTH) --scene-index 0 \
		--stride 1 --screenshot docs/images/view_4d.png --size 1200x720 --overwrite

clean:
	rm -rf $(VENV) build *.egg-info
