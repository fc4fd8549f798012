# Every target runs in bash with the workspace environment (.ws/env.sh) sourced.
# `make setup` installs and builds everything (idempotent); the others set up first.
SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

ENV := source .ws/env.sh
PYTEST_ARGS ?= -q
BENCH_ARGS ?=

.PHONY: help setup test bench demo clean fuzz soak hostile

help:
	@echo "make demo   set up if needed, then run the demo"
	@echo "make test   set up if needed, then all tests (unit + rostest), one summary line"
	@echo "make bench  set up if needed, then the benchmarks (docs/benchmarks.md, results/bench/);"
	@echo "           BENCH_ARGS=\"--quick --only NAME\" passes options to bench/run.py"
	@echo "make fuzz   the fuzz tests with many examples (FUZZ_ARGS=\"--examples N --seed S\"), docs/reliability.md"
	@echo "make soak   simulator + 8 detectors + localizer for SOAK_ARGS=\"--minutes 30\" of sim time: RSS, drops, error"
	@echo "make hostile  every hostile-input test (future stamps, NaN, floods, pauses, two localizers, map files;"
	@echo "           unit + rostest through a real master), docs/reliability.md; figures in results/hostile/"
	@echo "make setup  install apt packages, the venv and the catkin workspace (.venv/, .ws/)"
	@echo "make clean  remove the venv, the workspace and results/ (but the tracked results/bench/results.json)"

setup:
	@bash tools/setup.sh

test: setup
	@$(ENV) && python -m pytest $(PYTEST_ARGS) test/unit test/integration

bench: setup
	@$(ENV) && python bench/run.py $(BENCH_ARGS)

demo: setup
	@$(ENV) && bash tools/demo.sh

FUZZ_ARGS ?=
SOAK_ARGS ?=

fuzz: setup
	@$(ENV) && python tools/fuzz.py $(FUZZ_ARGS)

soak: setup
	@$(ENV) && python tools/soak.py $(SOAK_ARGS)

hostile: setup
	@$(ENV) && ARUCO_RING_HOSTILE=1 python -m pytest $(PYTEST_ARGS) test/unit/test_hostile_input.py \
		test/unit/test_map_limits.py test/integration/test_node_bad_input.py test/integration/test_rostests.py -k "hostile or map_limits or bad_input"

clean:
	rm -rf .venv .ws .pytest_cache .hypothesis
	@# results/: everything but the tracked benchmark keys (results/bench/results.json)
	@if [ -d results ]; then find results -mindepth 1 -maxdepth 1 ! -name bench -exec rm -rf {} +; \
		[ -d results/bench ] && find results/bench -mindepth 1 -maxdepth 1 ! -name results.json -exec rm -rf {} +; true; fi
