# The README's two commands: `make run` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
HOST   ?= 127.0.0.1
PORT   ?= 8000

.PHONY: run test install install-test browser bench fuzz soak lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: $(VENV)/.installed pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

install: $(VENV)/.installed

install-test: $(VENV)/.installed-test

# Debian's chromium for the dashboard's end-to-end test; the test skips with a reason if it is absent.
browser:
	@command -v chromium >/dev/null 2>&1 || ( command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ] && \
	  (apt-get update -qq >/dev/null 2>&1; DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1) ) || \
	  echo "note: chromium not installed; the browser test will be skipped"

run: install
	$(BIN)/armserver serve --host $(HOST) --port $(PORT)

test: install-test browser
	$(BIN)/python -m pytest -q

bench: install-test
	$(BIN)/python bench/kinematics.py

fuzz: install-test
	ARMSERVER_FUZZ_CASES=300 $(BIN)/python -m pytest -q tests/test_fuzz_api.py \
	  tests/test_fuzz_hostile.py tests/test_fuzz_dynamixel.py tests/test_fuzz_rbe3001.py
	@cat test-output/fuzz-report.txt

soak: install-test
	$(BIN)/python bench/soak.py --seconds 300

lint: install-test
	$(BIN)/python -m pip install --quiet ruff mypy
	$(BIN)/ruff check protocol kinematics app tests bench examples
	$(BIN)/mypy protocol kinematics

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
