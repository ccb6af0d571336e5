# One-command entry points. Setup is idempotent (scripts/setup.sh keeps a stamp in .venv).
VENV ?= .venv
PY := $(VENV)/bin/python
DATA ?= ../shared/data
# the shared data folder for lln-demo's default dataset and the tests (installed code never guesses it)
export LLN_DATA ?= $(abspath $(DATA))
NORDLAND := aligned:$(DATA)/nordland_trimmed/summer,$(DATA)/nordland_trimmed/winter,1

.PHONY: setup test main results train whitening loo bench bench-map bench-scale bench-writers bench-fleet bench-fleet-milvus colcon clean

setup:
	bash scripts/setup.sh

test: setup
	$(PY) -m pytest -q test

# the main job: a map from one traverse, queried with another through the ROS 2 nodes
main: setup
	bash scripts/main_job.sh $(ARGS)

# docs/results.md and docs/results/*.png from ../shared/data (~5 min with a warm feature cache)
results: setup
	bash scripts/results.sh $(ARGS)

# the shipped head, lln_ros/weights/lln_efficientnet_lite0_stage6.pt, from ../shared/data: the recipe that
# wins leave-one-dataset-out (docs/generalisation.md: prior, every tuple, 4 epochs) on every real set
# (Nordland: its training part 0:0.6, validated on 0.6:0.7; the test split 0.7:1 is never touched)
# ~10 min + features
RTABMAP := loop:$(DATA)/rtabmap_loop,$(DATA)/rtabmap_loop/samples_GT.bmp
ESSEX := vprbench:$(DATA)/essex3in1
TUM := poses:$(DATA)/tum_fr1rpy,15,0.3,2,3
train: setup
	$(VENV)/bin/lln-train --range 0:0.6 --val-range 0.6:0.7 --out out/train --epochs 4 --tuples-per-epoch 0 \
	  --norm-prior 1 --data $(NORDLAND) --val $(NORDLAND) --data $(RTABMAP) --val $(RTABMAP) \
	  --data $(ESSEX) --val $(ESSEX) --data $(TUM) --val $(TUM) $(ARGS)
	cp out/train/best.pt lln_ros/weights/lln_efficientnet_lite0_stage6.pt

# the learned whitenings (lln_ros/core/whitening.py): the landmark first stage's,
# lln_ros/weights/whiten_efficientnet_lite0_stage6.npz, from Nordland's training part 0:0.6 (summer/winter
# pairs), and S's, whiten_similarity_..., from the four training sets, each weighing the same
# (docs/method.md, Whitening; ~2 min + features)
whitening: setup
	$(PY) scripts/learn_whitening.py --data $(NORDLAND) --range 0:0.6 --cache $${LLN_CACHE:-cache/features} $(ARGS)
	$(PY) scripts/learn_whitening.py --data $(NORDLAND) --data $(RTABMAP) --data $(ESSEX) --data $(TUM) --range 0:0.6 \
	  --balance --purpose similarity --cache $${LLN_CACHE:-cache/features} $(ARGS)

# leave-one-dataset-out validation of training recipes (docs/generalisation.md; ~1 h on 2 idle cores)
loo: setup
	bash scripts/loo.sh $(ARGS)
	$(PY) scripts/loo_md.py out/loo

bench: setup
	$(PY) bench/bench_core.py

# map store at 1k / 10k / 100k keyframes (~5 min, ~2 GB in /tmp); table on stdout, plot in out/
bench-map: setup
	$(PY) bench/bench_map.py $(ARGS)

# Nordland test split in maps padded with real distractor keyframes (docs/benchmarks.md, Accuracy at scale)
bench-scale: setup
	nice -n 10 $(PY) bench/bench_accuracy_at_scale.py --data $(DATA) $(ARGS)

# many writer processes on one map: a real Milvus server beside SQLite, then a 10-min soak with a
# SIGKILL and a server restart (docs/map_store.md, Many writers; ~20 min; loopback-only namespace)
bench-writers: setup
	$(PY) test/milvus_loopback.py -- $(PY) bench/bench_milvus_writers.py $(ARGS)

# two robots on one map through the nodes: Nordland summer (robot A) and winter (robot B) at once
# (docs/map_store.md, Two robots through the nodes; ~4 min, ~20 on the server); -milvus: on a real server
bench-fleet: setup
	$(PY) bench/bench_fleet.py --data $(DATA) $(ARGS)

bench-fleet-milvus: setup
	$(PY) test/milvus_loopback.py --server -- $(PY) bench/bench_fleet.py --data $(DATA) --map milvus $(ARGS)

colcon: setup
	$(VENV)/bin/colcon build --base-paths . --build-base build --install-base install

clean:
	rm -rf build install log .pytest_cache
