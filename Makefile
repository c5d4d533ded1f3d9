# Every target that runs code first does all set-up on a bare Debian machine:
# the LLVM runtime Mitsuba's LLVM backend needs, a virtual environment, and the package.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.jprt-installed

.PHONY: setup llvm test test-slow view-deps view demo bench bench-rrf bench-datadriven bench-wavelet bench-sg bench-sg-environment bench-mrt bench-atlas clean

setup: llvm $(STAMP)

# Dr.Jit's LLVM backend crashes with Debian's default libLLVM 14/15; install libLLVM 19 when no
# libLLVM >= 16 is present (jprt/render/setup.py finds it and sets DRJIT_LIBLLVM_PATH).
llvm:
	@if ls /usr/lib/*/libLLVM-1[6-9]*.so* /usr/lib/*/libLLVM-[2-9][0-9]*.so* /usr/lib/llvm-1[6-9]/lib/libLLVM*.so* /usr/lib/llvm-[2-9][0-9]/lib/libLLVM*.so* >/dev/null 2>&1; then \
	  echo "libLLVM >= 16 present"; \
	else \
	  echo "installing libllvm19 (Mitsuba's LLVM backend needs libLLVM >= 16)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq libllvm19; \
	fi

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test,ray,metrics,view]"
	touch $(STAMP)

# the import layers first (pyproject.toml [tool.importlinter]): seconds, and a broken layer is a design error
test: setup
	$(VENV)/bin/lint-imports
	$(PY) -m pytest -q -n 3 --dist loadfile tests

test-slow: setup view-deps
	$(PY) -m pytest -q -m slow tests

# the viewer's browser test: Debian's Chromium (driven through Playwright, no browser download)
view-deps: setup
	@command -v chromium >/dev/null 2>&1 || { \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium; }
	$(PY) -m pip install -q -e ".[view-test]"

# the export tests' tools: Node.js and npm (Debian's), the npm packages pinned in tests/js/package.json
# (gltf-validator, three, @gltf-transform/core) into tests/js/node_modules, Chromium, and the
# export extra (jax2onnx, onnxruntime, pygltflib)
.PHONY: export-deps
export-deps: setup
	@command -v node >/dev/null 2>&1 && command -v npm >/dev/null 2>&1 && command -v chromium >/dev/null 2>&1 || { \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq nodejs npm chromium; }
	cd tests/js && npm ci --no-audit --no-fund 2>/dev/null || npm install --no-audit --no-fund
	$(PY) -m pip install -q -e ".[export,view-test]"

# make view RUN=results/<experiment>/<config hash>
view: setup
	$(VENV)/bin/jprt view $(RUN)

demo: setup
	$(PY) -m jprt.cli run experiments/rrf_cornell.py --preset demo

bench: setup
	$(PY) benchmarks/sphere.py

bench-rrf: setup
	$(PY) benchmarks/rrf_cornell.py

bench-datadriven: setup
	$(PY) benchmarks/datadriven.py

# the reruns first: wavelet_prt.py copies their spread (psnr_spread_reruns) into its JSON
bench-wavelet: setup
	$(PY) benchmarks/wavelet_reruns.py
	$(PY) benchmarks/wavelet_prt.py

bench-sg: setup
	$(PY) benchmarks/sg_lightfield.py

bench-sg-environment: setup
	$(PY) benchmarks/sg_environment.py

bench-mrt: setup
	$(PY) benchmarks/mrt.py

bench-atlas: setup
	$(PY) benchmarks/atlas.py

clean:
	rm -rf $(VENV) build *.egg-info
