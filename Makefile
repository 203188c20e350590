# Two commands on a fresh machine with Python 3.11, git and make: `make demo` and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export ROVER_TEST_DATA ?= $(abspath ../shared/data)

.PHONY: demo test test-fast lint bench check clean netns-tools

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@

demo: $(STAMP)
	$(BIN)/python -m rover.cli.demo

# ruff, then mypy through tools/typecheck.py (a link tree of the package in build/typecheck: mypy follows
# neither the editable install nor pyproject's package-dir); strict on the core, see [tool.mypy] in pyproject.toml.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python tools/typecheck.py

# The multi-host tests (tests/test_hosts.py) build network namespaces: they need root, iproute2 and
# nftables. As root on Debian, a missing nft is installed here; without it those tests fail loudly
# (ROVER_SKIP_NETNS=1 skips them).
netns-tools:
	@command -v nft >/dev/null || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null || \
		apt-get install -y -q nftables >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null 2>&1 && apt-get install -y -q nftables >/dev/null 2>&1; } || \
		echo "make: could not install nftables; tests/test_hosts.py will say what is missing"
	@command -v openssl >/dev/null || [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null || \
		apt-get install -y -q openssl >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null 2>&1 && apt-get install -y -q openssl >/dev/null 2>&1; } || \
		echo "make: could not install openssl; tests/test_certs.py will say what is missing"

# An independent ROS 2 client for tests/test_ros2_interop.py, in an environment of its own: zenoh-ros2-sdk
# on the Zenoh that rmw_zenoh pins for Jazzy (1.7), not on ours. Without it those tests fail saying to make
# it (ROVER_SKIP_INTEROP=1 skips them).
INTEROP := .venv-interop
$(INTEROP)/.installed: tests/ros2_interop/requirements.txt
	$(PYTHON) -m venv $(INTEROP)
	$(INTEROP)/bin/python -m pip install --quiet --upgrade pip
	$(INTEROP)/bin/python -m pip install --quiet -r tests/ros2_interop/requirements.txt
	touch $@

# The suite on both cores, then the multi-host tests two at a time (each lab has its own namespaces;
# a lab's hosts mostly wait on each other, so two labs share the cores without slowing either much),
# then the live session alone: it checks real-time order, which another lab's run would starve.
test: lint netns-tools $(INTEROP)/.installed
	$(BIN)/python -m pytest -q -n 2 -m "not netns" --durations=15
	$(BIN)/python -m pytest -q -n 2 -m "netns and not live" --durations=5
	$(BIN)/python -m pytest -q -m live

# The unit and contract tests only, on both cores: what to run while iterating (docs/contributing.md).
test-fast: $(STAMP) $(INTEROP)/.installed
	$(BIN)/python -m pytest -q -n 2 -m "not slow and not netns"

$(VENV)/.bench: pyproject.toml $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[test,bench]"
	touch $@

bench: $(VENV)/.bench
	$(BIN)/python bench/run_all.py

check: $(STAMP)
	$(BIN)/rover check pipeline.yaml

clean:
	rm -rf $(VENV) $(INTEROP) rover-out build *.egg-info
