# The two commands of the README: `make demo` (a recorded, constrained trial) and `make test`.
# Both create or reuse .venv (Python 3.11) and install the pinned requirements once; later runs
# only re-install when requirements*.txt, setup.py or package.xml change, or a top-level package
# comes or goes (the editable install maps each by name).

PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DATASET ?= ../shared/datasets/pusht_cchi_v7_replay.zarr

.PHONY: setup demo test bench evaluation clean-venv

$(STAMP): requirements.txt requirements-test.txt setup.py package.xml $(wildcard */__init__.py)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check -r requirements.txt -r requirements-test.txt
	$(BIN)/python -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	@touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/trial --scenario center_0.2 --configuration r_g10_p_safe --seed 100000 \
		--output trials/demo-$$(date +%Y%m%d-%H%M%S)

test: $(STAMP)
	$(BIN)/ruff check .
	PUSHT_ZARR=$(DATASET) $(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python scripts/bench_sim.py
	$(BIN)/benchmark_policy
	$(BIN)/python scripts/bench_constraints.py --dataset $(DATASET)
	$(BIN)/python scripts/bench_zones.py
	$(BIN)/python scripts/bench_clock.py  # idle, then with a load it starts itself
	$(BIN)/python scripts/bench_realtime.py  # idle, then with a load it starts itself

# Table I's protocol (25 scenes) for every row, then our main rows on 100 scenes beside it,
# then the zones that move (hands) on 100 scenes, body-safe beside unconstrained.
HUNDRED_SEED_ROWS ?= none r_g10 ddim10_none ddim10_r_g10_p ddim10_r_g10_p_safe
# The main report's scenarios; the small-obstacle ones have a report of their own
# (docs/body_safe_sliding.md names its command).
REPORT_SCENARIOS ?= left_0.1 left_0.5 center_0.1 center_0.2 l_shape two_zones moving_hand \
	center_0.2_grid camera_center
evaluation: $(STAMP)
	$(BIN)/evaluate --scenarios $(REPORT_SCENARIOS) --output docs/evaluation
	$(BIN)/evaluate --episodes 100 --scenarios paper --configs $(HUNDRED_SEED_ROWS) \
		--output docs/evaluation_100
	$(BIN)/evaluate --episodes 100 --scenarios moving --configs ddim10_none \
		ddim10_r_g10_p_safe --output docs/evaluation_moving

clean-venv:
	rm -rf $(VENV)
