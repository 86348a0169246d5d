# sorolearn: learned-environment RL for pneumatic soft arms. `make help` lists the targets.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# the ROS 2 wheels (PyPI) are part of the default setup: the real-arm safety tests need them
EXTRAS ?= dev,ros,docs

.DEFAULT_GOAL := help
.PHONY: help setup setup-ros setup-cuda run quick test test-slow test-all lint bench figures docs clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; {printf "  %-10s %s\n", $$1, $$2}'

setup: ## create the virtual environment and install the project (editable), test tools, ROS 2 wheels, MkDocs
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e ".[$(EXTRAS)]"

setup-ros: ## the same as setup (kept for old instructions)
	$(MAKE) setup EXTRAS=dev,ros

setup-cuda: ## setup with JAX's CUDA 12 wheels: on a machine with an NVIDIA GPU (docs/gpu.md)
	$(MAKE) setup EXTRAS=dev,ros,docs,cuda

run: ## run the whole pipeline on the simulated arm (the embedded default)
	$(BIN)/python -m pipeline

quick: ## the whole pipeline shrunk to CI size
	$(BIN)/python -m pipeline experiment=quick

test: ## the fast test suite (CI runs it, then test-slow)
	$(BIN)/python -m pytest -m "not slow" -n 2

test-slow: ## the slow tests alone: the ROS 2 fault injection, integration runs, whole figures
	$(BIN)/python -m pytest -m slow -n 2

test-all: ## every test, slow ones included
	$(BIN)/python -m pytest -n 2

lint: ## ruff
	$(BIN)/ruff check .

bench: ## benchmarks: print side-by-side tables (ratios)
	$(BIN)/python -m bench

docs: ## build the documentation site into site/ (needs the docs extra: pip install -e ".[docs]")
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

clean: ## remove run outputs (artifacts included) and the built site
	rm -rf outputs multirun site

figures: ## the paper's Figs. 4-8 from the pipeline's artifacts (minutes on 2 cores) -> outputs/paper_figures/
	$(BIN)/python -m experiments.paper_figures
