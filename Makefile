# The two commands a fresh machine needs: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test setup clean-venv browser screenshots

$(STAMP): pyproject.toml
	@# Open3D's wheel loads libusb-1.0.so.0; a fresh Debian lacks it.
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/cellctl scan --scene smooth_cylinder --planner gnbv --dry-run-cut

# The tablet's browser test drives Debian's headless Chromium (playwright downloads no browser).
browser:
	@if ! command -v chromium >/dev/null; then \
		echo "installing chromium (the tablet's browser test)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	fi

# Two processes (pytest-xdist), each taking whole files: a file's tests run in order in one process and its
# module fixtures are made once, as in a plain `pytest -q`. Every test is written to pass on a loaded machine.
test: $(STAMP) browser
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

# Every README picture, made by the code itself from a fresh run: a t_piece scan seen by the Rerun
# viewer (headless: Xvfb and Mesa's Vulkan on the CPU), and the tablet's pages from its browser test.
SHOTS := docs/img
screenshots: $(STAMP) browser
	@if ! command -v xvfb-run >/dev/null || ! dpkg -s mesa-vulkan-drivers >/dev/null 2>&1; then \
		echo "installing xvfb and mesa-vulkan-drivers (the Rerun viewer, headless)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq xvfb mesa-vulkan-drivers >/dev/null; \
	fi
	rm -rf runs/screenshots
	$(BIN)/cellctl scan --scene t_piece --planner gnbv --out runs/screenshots --quiet
	xvfb-run -a -s "-screen 0 1600x1000x24" env WGPU_BACKEND=vulkan XDG_RUNTIME_DIR=/tmp WINIT_X11_SCALE_FACTOR=1 \
		$(BIN)/rerun --port 9897 --window-size 1400x900 --screenshot-to $(SHOTS)/viewer.png runs/screenshots/*/scan.rrd
	$(BIN)/python -c "from PIL import Image; im = Image.open('$(SHOTS)/viewer.png'); \
		im.convert('RGB').resize((1400, 900), Image.LANCZOS).save('$(SHOTS)/viewer.png', optimize=True)"
	SCRAPCELL_SCREENSHOTS=$(SHOTS) $(BIN)/python -m pytest -q tests/test_tablet_browser.py

clean-venv:
	rm -rf $(VENV)
