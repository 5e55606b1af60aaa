# Set-up and the two entry points of the README: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The reference splat converter and the formats' authors' own libraries (tests compare our splat readers/writers
# with them): @playcanvas/splat-transform (compressed PLY's author, a converter for the rest), @adobe/spz (Niantic's
# SPZ library built to WebAssembly), @mkkellogg/gaussian-splats-3d with its peer three.js (.ksplat's author).
# Installed into the checkout when node and npm exist, skipped (tests then skip with a reason) when they do not.
# The web viewer our splat files are rendered by (tests/seggaussian/io/test_web_viewer.py, in headless Chromium):
# Spark (@sparkjsdev/spark), the one of PlayCanvas's engine, Spark and GaussianSplats3D that reads all five of our
# formats (SPZ: versions 2 and 3, not 4); its peer three.js (>= 0.180) conflicts with GaussianSplats3D's pinned
# three@0.160.0, so it has its own folder, $(SPARK_DIR)/node_modules.
# CesiumJS (`cesium`, by the authors of glTF's KHR_gaussian_splatting) draws our .glb files in the same browser
# (tests/seggaussian/io/test_cesium_viewer.py); its own folder, $(CESIUM_DIR)/node_modules, keeps its dependencies
# apart.
SPLAT_TRANSFORM_VERSION := 3.7.0
NIANTIC_SPZ_VERSION := 0.2.3
GS3D_VERSION := 0.4.7
THREE_VERSION := 0.160.0
SPARK_VERSION := 2.2.0
SPARK_THREE_VERSION := 0.180.0
CESIUM_VERSION := 1.145.0
NODE_PACKAGES := @playcanvas/splat-transform@$(SPLAT_TRANSFORM_VERSION) @adobe/spz@$(NIANTIC_SPZ_VERSION) \
  @mkkellogg/gaussian-splats-3d@$(GS3D_VERSION) three@$(THREE_VERSION)
SPARK_PACKAGES := @sparkjsdev/spark@$(SPARK_VERSION) three@$(SPARK_THREE_VERSION)
CESIUM_PACKAGES := cesium@$(CESIUM_VERSION)
NODE_DIR := .node
SPARK_DIR := $(NODE_DIR)/spark
CESIUM_DIR := $(NODE_DIR)/cesium
NODE_STAMP := $(NODE_DIR)/.installed-$(SPLAT_TRANSFORM_VERSION)-spz$(NIANTIC_SPZ_VERSION)-gs3d$(GS3D_VERSION)-spark$(SPARK_VERSION)-cesium$(CESIUM_VERSION)
# The headless browser of the web viewer test: Debian's chromium (driven by the `playwright` Python package of the
# test extra through executable_path; `playwright install` is never run).
CHROMIUM := /usr/bin/chromium
# The two apt-get installs (libusb, chromium) take this lock in turn, so that `make -j3 setup` (.ci/run) can run
# them beside pip and npm.
APT_LOCK := /tmp/seggaussian-setup-apt.lock

.PHONY: setup demo test clean

setup: $(STAMP) $(NODE_STAMP) $(CHROMIUM)

# open3d's wheels link libusb-1.0; install it (Debian package) when the loader cannot find it.
$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  $$SUDO flock $(APT_LOCK) sh -c 'apt-get update -qq && apt-get install -y -qq libusb-1.0-0'; \
	fi
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[all]'
	@touch $(STAMP)

$(NODE_STAMP):
	@if command -v node >/dev/null 2>&1 && command -v npm >/dev/null 2>&1; then \
	  echo "installing $(NODE_PACKAGES) into $(NODE_DIR)/"; \
	  npm install --silent --no-audit --no-fund --prefix $(NODE_DIR) $(NODE_PACKAGES) \
	    && echo "installing $(SPARK_PACKAGES) into $(SPARK_DIR)/" \
	    && npm install --silent --no-audit --no-fund --prefix $(SPARK_DIR) $(SPARK_PACKAGES) \
	    && echo "installing $(CESIUM_PACKAGES) into $(CESIUM_DIR)/" \
	    && npm install --silent --no-audit --no-fund --prefix $(CESIUM_DIR) $(CESIUM_PACKAGES) \
	    && touch $(NODE_STAMP) \
	    || echo "npm install failed: the splat reference comparison and web viewer tests will be skipped"; \
	else \
	  echo "node/npm not found: the splat reference comparison and web viewer tests will be skipped"; \
	fi

# Debian's chromium (apt-get only when missing); a failed install leaves the web viewer test skipped with the reason.
$(CHROMIUM):
	@echo "installing chromium (headless browser of the web viewer test)"; \
	if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	$$SUDO flock $(APT_LOCK) sh -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium' \
	  || echo "chromium install failed: the web viewer test will be skipped"

# The main job, end to end on the embedded synthetic data.
demo: $(STAMP) $(NODE_STAMP)
	bash scripts/demo.sh

test: $(STAMP) $(NODE_STAMP) $(CHROMIUM)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

clean:
	rm -rf out .pytest_cache
