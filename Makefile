# Two commands do all the set-up on a fresh machine:
#   make demo   -> renders with the bundled default world and prints where the PNG went
#   make test   -> runs the test suite
# Both create .venv when needed and install torch==2.13.0 (CPU wheel) before the package.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.dsg-installed
export MUJOCO_GL ?= egl
export PYTHONUNBUFFERED := 1

.PHONY: demo test bench install clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test,rl,ray]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m dsg_gym.cli.demo

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) -m benchmarks.render --out render.json

clean:
	rm -rf $(VENV) build *.egg-info
