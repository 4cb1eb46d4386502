# Two commands do all the set-up on a fresh machine:
#   make demo   -> installs what the demo needs, renders with the bundled default world, prints where the PNG went
#   make test   -> installs the test extras too, runs ruff (lint and format check) and the test suite
# Both create .venv when needed and install torch==2.13.0 (CPU wheel) before the package, so pip never
# resolves torch itself (it would pick a CUDA build). Each install step has its own stamp in .venv:
# `make test` after `make demo` adds the extras; a changed pyproject.toml redoes the steps.
#   make smoke  -> builds the wheel and runs it from a fresh venv outside the checkout (.ci/wheel_smoke.sh)
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install -q
BASE := $(VENV)/.dsg-base
TEST := $(VENV)/.dsg-test
BENCH := $(VENV)/.dsg-bench
# the extras the tests import: test (pytest, hypothesis, ruff), rl (tests/test_env.py, tests/test_goal_env.py),
# ray (tests/test_collect_ray.py), capture (tests/test_photo_capture.py), bench (tests/test_pareto.py's plots),
# viewer (tests/test_viewer.py), video (tests/test_video.py); tests of an absent extra skip with a reason
TEST_EXTRAS := test,rl,ray,capture,bench,viewer,video
export MUJOCO_GL ?= egl
export PYTHONUNBUFFERED := 1
# pip retries dropped connections and resumes interrupted downloads (an older pip ignores the second)
export PIP_RETRIES ?= 10
export PIP_RESUME_RETRIES ?= 20

.PHONY: demo test bench smoke install clean

install: $(BASE)

# the venv, torch, and the package (editable) with its runtime dependencies only
$(BASE): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) --upgrade pip
	$(PIP) torch==2.13.0
	$(PIP) -e .
	touch $@

# .ci/install_extras.sh retries on a flaky network; an optional extra that still fails leaves the stamp unset
# (its tests skip with a reason, and the next `make test` tries again); a failed `test` extra stops here
$(TEST): $(BASE)
	bash .ci/install_extras.sh $(PY) $(TEST_EXTRAS); rc=$$?; if [ $$rc = 0 ]; then touch $@; fi; [ $$rc != 1 ]

$(BENCH): $(BASE)
	$(PIP) -e '.[bench]'
	touch $@

demo: $(BASE)
	$(PY) -m dsg_gym.cli.demo

test: $(TEST)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m pytest -q --durations=15 tests

bench: $(BENCH)
	$(PY) -m benchmarks.render --out render.json

smoke:
	bash .ci/wheel_smoke.sh

clean:
	rm -rf $(VENV) build *.egg-info
