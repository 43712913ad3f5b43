# ccrjax: everything a fresh clone needs, from python3 and make alone.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# JaxMARL, for benchmarks/jaxmarl_peer.py only: its own venv, never a ccrjax dependency.
PEER_VENV  := benchmarks/.peer-venv
PEER_PY    := $(PEER_VENV)/bin/python
PEER_STAMP := $(PEER_VENV)/.installed-stamp

.PHONY: install train demo test test-slow lint bench bench-peers sweep penalty-sweep tables report mutants clean

install: $(STAMP)

# Re-runs only when the package metadata changes, so `make install` is idempotent.
# setuptools' generic notice that an editable install imports from this folder (it does, by
# design) is filtered out; pip's and setuptools' other warnings still show.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# The main job: MADDPG with CCR on the hidden obstacle, 3 seeds at once (3 to 5 minutes on
# 2 CPU cores), into runs/<scenario>-<algo>-<variant>-<time>/; prints where the pictures are.
train: install
	$(PY) -m ccrjax.train --scenario hidden_obstacle --algo maddpg --variant ccr --seeds 3

# Random robots in every scenario: runs/demo/<scenario>.png and .gif.
demo: install
	$(PY) -m ccrjax.demo --out runs/demo

# The suite on both cores (one worker per test file), without the pipeline checks and the
# others of a minute or more, marked slow; test-slow runs those (CI runs both).
test: install
	$(PY) -m pytest -n 2 --dist loadfile -m "not slow"

test-slow: install
	$(PY) -m pytest -m slow

lint: install
	$(PY) -m ruff check ccrjax tests benchmarks experiments

bench: install
	$(PY) benchmarks/env_throughput.py
	$(PY) benchmarks/train_throughput.py --variants plain ccr lagrangian
	$(PY) benchmarks/replay_compare.py

# The searches of docs/protocol.md: CCR's lambda and the pessimistic penalty, alike, one
# vmapped program per scenario and learner, into runs/search/<variant> unless SWEEP_ARGS
# names another --out (the committed ones: --out experiments/results/search/<variant> --force).
# One scenario and learner alone: python -m ccrjax.sweep --help.
SWEEP_ARGS ?=
sweep: install
	$(PY) experiments/search.py --variant ccr $(SWEEP_ARGS)

penalty-sweep: install
	$(PY) experiments/search.py --variant pessimistic $(SWEEP_ARGS)

# The paper's Tables I and II under the protocol, into runs/tables unless TABLES_ARGS
# names another --out; resumable (python experiments/tables.py --help gives its cost).
TABLES_ARGS ?=
tables: install
	$(PY) experiments/tables.py $(TABLES_ARGS)

# The results report, experiments/results/README.md, from the committed result files
# (make tables writes it too when its --out is under experiments/results).
report: install
	$(PY) -m experiments.results_report

# Mutation check: small bugs in the core code (tools/mutants.toml), each caught by named
# tests; every file is restored afterwards. Exit status 1 if a mutant survives.
mutants: install
	$(PY) tools/mutants.py

# Peer comparison: JaxMARL's MPE simple_spread, measured the same way, in its own venv; with
# JAXMARL_IPPO=<a JaxMARL checkout>/baselines/IPPO/ippo_ff_mpe.py, also its IPPO training
# against ccrjax's (the pip package has no baselines).
JAXMARL_IPPO ?=
bench-peers: install $(PEER_STAMP)
	$(PEER_PY) benchmarks/jaxmarl_peer.py
	@if [ -n "$(JAXMARL_IPPO)" ]; then \
	  $(PY) benchmarks/ippo_versus_jaxmarl.py --jaxmarl-ippo "$(JAXMARL_IPPO)"; \
	else echo "IPPO against JaxMARL's: give JAXMARL_IPPO=<checkout>/baselines/IPPO/ippo_ff_mpe.py"; fi

$(PEER_STAMP):
	@test -x $(PEER_PY) || $(PYTHON) -m venv $(PEER_VENV)
	$(PEER_PY) -m pip install --quiet --upgrade pip
	$(PEER_PY) -m pip install --quiet jaxmarl distrax
	@touch $(PEER_STAMP)

clean:
	rm -rf $(VENV) $(PEER_VENV) runs .pytest_cache
