# One-command set-up: every target creates .venv and installs the pinned dependencies when missing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
REQS := requirements/base.txt requirements/nodeps.txt requirements/dev.txt pyproject.toml

.PHONY: test install install-cuda demo head-show clean-venv web

install: $(STAMP)

$(STAMP): $(REQS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements/base.txt -r requirements/dev.txt
	$(PY) -m pip install -q --no-deps -r requirements/nodeps.txt
	$(PY) -m pip install -q --no-deps --no-build-isolation -e .
	@# The native CPU code (the rasterizer; the avatar's placement loops; the SSIM), built now, side by side,
	@# instead of inside the first command that renders (a minute of one core). Without a compiler each warns,
	@# and the PyTorch paths run.
	$(PY) -c "from geoavatar.render import cpu_backend; cpu_backend.load_extension()" & \
	  $(PY) -c "from geoavatar.avatar import fused; fused.load_extension()" & \
	  $(PY) -c "from geoavatar.imaging import quality; quality.load_extension()"; wait
	touch $(STAMP)

# On a machine with CUDA: gsplat is then used automatically for rendering and training.
install-cuda: $(STAMP)
	$(PY) -m pip install -q "gsplat==1.5.3" packaging

test: $(STAMP)
	$(PY) -m pytest -q

# The main job, as a user's video goes: generate a subject, train, track the test frames against the avatar,
# evaluate, render (256 px); read demo_output/report.md.
demo: $(STAMP)
	$(VENV)/bin/geoavatar demo --out demo_output

# The browser player's bundle (geoavatar/web/static/player.js, committed): rebuild it after editing web/.
# Needs Node 20 and npm; `make` and pip use the committed bundle and need neither.
web:
	cd web && npm ci --no-audit --no-fund && npm run build

head-show: $(STAMP)
	$(VENV)/bin/geoavatar head show --out head.png

clean-venv:
	rm -rf $(VENV)
