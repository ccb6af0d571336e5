# One-command entry points. Setup is idempotent (scripts/setup.sh keeps a stamp in .venv).
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup test main bench bench-map colcon clean

setup:
	bash scripts/setup.sh

test: setup
	$(PY) -m pytest -q test

# the main job: a map from one traverse, queried with another through the ROS 2 nodes
main: setup
	bash scripts/main_job.sh $(ARGS)

bench: setup
	$(PY) bench/bench_core.py

# map store at 1k / 10k / 100k keyframes (~5 min, ~2 GB in /tmp); table on stdout, plot in out/
bench-map: setup
	$(PY) bench/bench_map.py $(ARGS)

colcon: setup
	$(VENV)/bin/colcon build --base-paths . --build-base build --install-base install

clean:
	rm -rf build install log .pytest_cache
