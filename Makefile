# rlexp: `make train` and `make test` set everything up on a fresh machine (Python 3.10+).
# Re-running does no work: each install step leaves a stamp in .venv/.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
ARGS ?=
export MUJOCO_GL ?= egl

.PHONY: install install-all train test test-slow test-gpu test-slurm test-package lint format bench bench-e2e bench-envs results-backends results-classic clean

$(VENV)/.created:
	$(PYTHON) -m venv $(VENV)
	touch $@

# torch first: anything that depends on torch must find it installed. Which build is yours to choose:
#   TORCH_INDEX unset (default): pip's own index. On PyPI, torch 2.13.0 for Linux x86_64 is the CUDA
#     build (~2.5 GB with its nvidia-* wheels); a pip configured with a local CPU wheel (as the
#     machine rlexp is developed on) gets that.
#   make install TORCH_INDEX=https://download.pytorch.org/whl/cpu     CPU only (~0.9 GB): laptops, CI
#   make install TORCH_INDEX=https://download.pytorch.org/whl/cu128   CUDA 12.8 build, for GPU nodes
TORCH_VERSION ?= 2.13.0
TORCH_INDEX ?=
$(VENV)/.torch: $(VENV)/.created
	$(PY) -m pip install --disable-pip-version-check torch==$(TORCH_VERSION) \
		$(if $(TORCH_INDEX),--index-url $(TORCH_INDEX) --extra-index-url https://pypi.org/simple)
	touch $@

# Two installs, each with a stamp (`make test` after `make train` adds only the rest), both with the
# versions CI tests (constraints.txt; pyproject.toml has the ranges rlexp accepts):
#   core: what `make train` needs (rlexp and its dependencies: the Gymnasium MuJoCo suite, the native
#     tasks, TensorBoard and JSONL logs, checkpoints, sweeps on one machine, eval, TorchScript export);
#     1.2 GB with the CPU torch wheel (torch alone 0.9 GB), 50 packages
#   all: every extra (W&B, SLURM, Optuna, video, report, ONNX export, Box2D, EnvPool) and the dev tools
#     the tests use: 2.7 GB, 123 packages (EnvPool and its assets 0.74 GB of it)
$(VENV)/.installed-core: $(VENV)/.torch pyproject.toml setup.py constraints.txt
	$(PY) -m pip install --disable-pip-version-check -c constraints.txt -e .
	touch $@

$(VENV)/.installed-all: $(VENV)/.installed-core
	$(PY) -m pip install --disable-pip-version-check -c constraints.txt -e ".[all,dev]"
	touch $@

## The core install (what `make train` runs); `make install-all` adds every extra and the dev tools.
install: $(VENV)/.installed-core
install-all: $(VENV)/.installed-all

## Train PPO on the default task (HalfCheetah-v5); pass Hydra overrides with ARGS="env=hopper seed=3".
train: $(VENV)/.installed-core
	$(PY) train.py $(ARGS)

## The default test suite (what CI runs): TEST_WORKERS processes, each test file on one of them
## (its module fixtures built once); most tests wait on the train.py processes they start.
TEST_WORKERS ?= 2
test: $(VENV)/.installed-all
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile $(ARGS)

## Learning tests (minutes to hours): the agent really improves.
test-slow: $(VENV)/.installed-all
	$(PY) -m pytest -q -m slow $(ARGS)

## rlexp as users get it: its wheel and examples/user_project's in a fresh virtualenv (also in `test`).
test-package: $(VENV)/.installed-all
	$(PY) -m pytest -q -m package $(ARGS)

## The GPU path (tests marked `gpu`, skipped without CUDA): a batched torch env on cuda trained,
## resumed, evaluated and exported; trainer.device=auto's choices.
test-gpu: $(VENV)/.installed-all
	$(PY) -m pytest -q -m gpu $(ARGS)

## Sweeps on a real SLURM cluster (tests marked `slurm`): starts a local single-node cluster first
## (scripts/local-slurm.sh; root, installs slurm-wlm + munge with apt-get when missing).
test-slurm: $(VENV)/.installed-all
	scripts/local-slurm.sh start
	$(PY) -m pytest -q -m slurm $(ARGS)

lint: $(VENV)/.installed-all
	$(VENV)/bin/ruff check src tests train.py setup.py examples/user_project
	$(VENV)/bin/ruff format --check src tests train.py setup.py examples/user_project

format: $(VENV)/.installed-all
	$(VENV)/bin/ruff format src tests train.py setup.py examples/user_project
	$(VENV)/bin/ruff check --fix src tests train.py setup.py examples/user_project

# The benchmarks' baselines are the `bench` extra, installed by name so rlexp's editable install is
# left alone; they need no other torch / gymnasium / numpy than rlexp's (checked with pip install
# --dry-run).
$(VENV)/.bench: $(VENV)/.installed-all
	$(PY) -m pip install --disable-pip-version-check "stable-baselines3>=2.9,<3" "py-spy>=0.3"
	touch $@

## PPO env-steps/s: rlexp vs Stable-Baselines3, CleanRL-style PyTorch and the floors, plus start-up
## (docs/performance.md); writes benchmarks/results.md. ARGS="--quick" for a smoke run (< 2 min).
bench: $(VENV)/.bench
	$(PY) benchmarks/ppo_throughput.py $(ARGS)

## What users wait for (#18, #15): `python train.py` from launch to exit against an SB3 script doing
## the same job, with the time to CleanRL's return; a section of benchmarks/results.md per row.
## ARGS="--row whole" (61,440 steps, 3 alternating rounds, ~5 min on 2 cores) or ARGS="--row e2e"
## (1M steps with evaluation, rlexp eval sync + async and SB3, ~35 min); --env, --anchor, --variant.
bench-e2e: $(VENV)/.bench
	$(PY) benchmarks/end_to_end.py $(ARGS)

## Batched envs and scale (#31): collection env-steps/s of HalfCheetah-v5 at 1, 8, 64 envs on the
## gymnasium, gymnasium_async and envpool backends and raw EnvPool (docs/performance.md); ~10 min.
bench-envs: $(VENV)/.installed-all
	$(PY) benchmarks/env_scale.py $(ARGS)

## The backends' learning (#31): +experiment=mujoco_throughput on gymnasium and envpool, HalfCheetah
## and Hopper, seeds 1 2 3, 1M steps each, launch to exit and returns (docs/performance.md).
results-backends: $(VENV)/.installed-all
	$(PY) benchmarks/backend_learning.py $(ARGS)

## Learning, measured (#28): the classic-control presets (+experiment=cartpole_ppo, acrobot_ppo,
## pendulum_ppo, lunar_lander_ppo) x seeds 0 1 2, one run at a time, and the steps and seconds each
## takes to its threshold (docs/results.md, "Classic control"); ~20 min on 2 cores.
## ARGS="--presets cartpole_ppo --seeds 0" for one run, ARGS="--out FILE" to keep the table.
results-classic: $(VENV)/.installed-all
	$(PY) benchmarks/classic_control.py $(ARGS)

clean:
	rm -rf $(VENV) outputs .pytest_cache
