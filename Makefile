# Two entry points, both self-contained on a fresh machine:
#   make demo   set up .venv and run the main job on the built-in part
#   make test   set up .venv and run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
TORCH_CPU := torch==2.13.0

.PHONY: demo test setup clean

setup: $(STAMP)

# The CPU build of torch goes in first: the project's torch requirement is a range that 2.13.0 satisfies,
# so pip keeps it instead of pulling a multi-GB CUDA build. open3d needs the Debian package libusb-1.0-0;
# it is installed when missing, apt is available and we are root; so is Debian's chromium, which the HTML report's
# headless-browser test drives (a browser that downloads itself cannot work offline).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH_CPU)
	$(BIN)/python -m pip install -q -e '.[test]'
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing libusb-1.0-0 (open3d needs it)"; \
	    apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	    (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libusb-1.0-0 >/dev/null); \
	  else echo "warning: open3d needs libusb-1.0-0 (apt-get install libusb-1.0-0)"; fi; \
	fi
	@if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    echo "installing chromium (the HTML report's browser test)"; \
	    apt-get install -y -q chromium >/dev/null 2>&1 || \
	    (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1) || \
	    echo "warning: chromium could not be installed; the browser test will be skipped"; \
	  else echo "warning: no chromium (apt-get install chromium): the browser test will be skipped"; fi; \
	fi
	$(BIN)/python -c "import torch, open3d, h5py, trimesh; print('environment ready: torch', torch.__version__)"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m inspection demo --out demo_output

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

clean:
	rm -rf $(VENV) demo_output
