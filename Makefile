# The README's two commands: `make run` and `make test`.
# The interpreter the venv is made from: Debian's python3 where there is one, else the first
# python3 on the PATH. On this project's machines the PATH's python3 is a pyenv build
# (`--enable-shared`, without `--enable-optimizations`: no profile-guided or link-time
# optimisation); Debian's is one executable with the interpreter linked in, and it runs the
# server's Python faster (one rbe3001's sample 92-102 -> 67-87 µs in four alternated runs,
# docs/performance.md "Session 20"). `make PYTHON=python3.12` picks another; an existing .venv
# is kept (`make clean` first).
PYTHON ?= $(or $(wildcard /usr/bin/python3),python3)
VENV   ?= .venv
BIN    := $(VENV)/bin
HOST   ?= 127.0.0.1
PORT   ?= 8000

.PHONY: run test test-run test-loaded test-deps install install-test browser mosquitto stress-ng run-lab bench bench-peers bench-lab fuzz soak lint check-lerobot clean

$(BIN)/python:
	@missing="$$($(PYTHON) -c 'import ensurepip' 2>/dev/null || echo python3-venv)"; $(apt_missing)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# (app/links/_restpoll.c is built by the install where a C compiler and Python's headers are
# found; else the poll thread's rounds run in Python alone. `make test` installs both first.)
$(VENV)/.installed: $(BIN)/python pyproject.toml app/links/_restpoll.c
	$(BIN)/python -m pip install --quiet -e .
	touch $@

# (the test extras in one install with the package: `make test` on a fresh clone builds it once)
$(VENV)/.installed-test: $(BIN)/python pyproject.toml app/links/_restpoll.c
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(VENV)/.installed $@

install: $(VENV)/.installed

install-test: $(VENV)/.installed-test

# What the tests need from Debian, found the one way the tests find it (tests/_deps.py): each
# target installs the missing packages with apt-get (as root, or through a password-less sudo)
# and FAILS if a program is still missing afterwards; a test never skips for want of one.
# (cc and Python.h before the package is installed: app/links/_restpoll.c is built then)
TEST_TOOLS := chromium mosquitto mosquitto_passwd node cc Python.h
# (the Debian packages named in the shell's $$missing, if any: apt-get installs them or it fails;
# Debian's python3 makes venvs only with its python3-venv, which `$(BIN)/python` asks for so)
define apt_missing
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then sudo=""; \
	  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then sudo="sudo -n"; \
	  else echo "error: missing Debian packages: $$missing (run \`sudo apt-get install $$missing\`, or make as root)" >&2; exit 1; fi; \
	  command -v apt-get >/dev/null 2>&1 || { echo "error: missing $$missing and no apt-get to install it" >&2; exit 1; }; \
	  echo "apt-get install $$missing"; \
	  $$sudo apt-get update -qq || true; \
	  $$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing \
	    || { echo "error: apt-get could not install $$missing" >&2; exit 1; }; \
	fi
endef
define need
	@missing="$$($(PYTHON) tests/_deps.py packages $(1))"; $(apt_missing); \
	$(PYTHON) tests/_deps.py check $(1)
endef

test-deps:
	$(call need,$(TEST_TOOLS))

# Debian's chromium for the dashboard's browser tests.
browser:
	$(call need,chromium)

# Debian's mosquitto for the MQTT tests (they start their own broker on a free loopback port)
# and for `make run-lab`.
mosquitto:
	$(call need,mosquitto mosquitto_passwd)

stress-ng:
	$(call need,stress-ng)

# A local mosquitto (MQTT on 127.0.0.1:1883, MQTT over WebSocket on 127.0.0.1:9001, anonymous,
# loopback only) and the server publishing to it; the lab view is http://HOST:PORT/lab.html.
LAB_DIR ?= /tmp/armserver-lab
run-lab: install mosquitto
	@mkdir -p $(LAB_DIR)
	@printf 'persistence false\nlistener 1883 127.0.0.1\nallow_anonymous true\nlistener 9001 127.0.0.1\nprotocol websockets\n' > $(LAB_DIR)/mosquitto.conf
	@PATH="$$PATH:/usr/sbin"; mosquitto -c $(LAB_DIR)/mosquitto.conf & MQ=$$!; \
	  trap 'kill $$MQ 2>/dev/null' EXIT INT TERM; \
	  ARMSERVER_MQTT_URL=mqtt://127.0.0.1:1883 $(BIN)/armserver serve --host $(HOST) --port $(PORT)

run: install
	$(BIN)/armserver serve --host $(HOST) --port $(PORT)

# Two parts: the tests that may share the machine on four workers (a file per worker at a time,
# the heaviest files first: tests/_scheduling.py, from tests/file_seconds.json, which
# `python tools/test_seconds.py` writes from the JUnit reports a run leaves in test-output/;
# most of a test's time is the simulated arms moving in real time, not CPU: four workers kept
# the two cores 65 % busy), then the browser tests and those that time the server itself
# (`serial`, tests/conftest.py) in two lanes side by side (SERIAL_LANES=2, the default since
# session 15): the tests that measure a speed or a hold one after another in one, the browser
# tests and the rest in the other (157-180 s against 230-311 s one at a time; SERIAL_LANES=1
# runs them one at a time). The lanes are tests/_scheduling.py's: since pytest 9.2, xdist's own
# `xdist_group` no longer groups anything, and the serial part ran any two of its tests side by
# side (two pages, two timing tests) until session 28. The page's drawn tip is judged against
# the very sample it drew, its lag apart (1 s): a page sharing the cores was the lanes' one
# failure in session 14 (a drawn tip 60 mm behind on a slow hour). TEST_WORKERS=6 runs the
# first part on six (211 s against 252 s on a quiet host), not the default: on a slow host hour
# it failed tests whose simulated buses answer from the test's own process.
# Side by side with the first part, at a lower priority, the serial part broke a test or two a
# run: under `chrt -i 0` or `nice -n 19` the first part's simulators that answer from a test's
# own process missed their 50 ms reply timeouts while the browser tests ran; under `nice -n 10`
# four workers' threads still took enough of the cores from the browser tests that the
# dashboard's drawn tip lagged (session 12).
# ARMSERVER_STRICT_SKIPS=1 (`.ci/run` sets it) makes any skip a failure.
TEST_WORKERS ?= 4
SERIAL_LANES ?= 2
SERIAL_ARGS  := $(if $(filter-out 1,$(SERIAL_LANES)),-n $(SERIAL_LANES) --dist loadgroup,)
test: test-deps install-test
	$(MAKE) --no-print-directory test-run

# (the serial part runs even if the parallel one failed: one run shows every failure)
# The safety state machine (tests/test_safety_machine.py) runs 8 examples per arm here (about
# 20 s each: every rule and contract check comes up), the same every run; more with ARMSERVER_SAFETY_EXAMPLES (and
# ARMSERVER_SAFETY_RANDOM=1). Not a time budget: an example skipped for time in one run and not
# in Hypothesis's second look at it made Hypothesis report FlakyStrategyDefinition, not a result.
# PYTHONDONTWRITEBYTECODE is emptied for the run (Python then writes its caches, __pycache__,
# git-ignored): where it is set, as on this project's machines, every pytest worker rewrote all
# 142 test files' asserts at each start and every `armserver serve` a test starts compiled the
# server anew (a skip-everything run of the first part: 29 s, 13 s with the caches).
test-run:
	rc=0; export PYTHONDONTWRITEBYTECODE=; \
	  $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not serial" --durations=15 \
	    --junitxml=test-output/junit-parallel.xml || rc=$$?; \
	  ARMSERVER_SAFETY_EXAMPLES=$${ARMSERVER_SAFETY_EXAMPLES:-8} \
	    $(BIN)/python -m pytest -q $(SERIAL_ARGS) -m serial --durations=5 \
	    --junitxml=test-output/junit-serial.xml || rc=$$?; \
	  exit $$rc

# `make test` beside a CPU load: stress-ng keeps LOAD_CPUS cores busy for the whole run, as a
# shared machine does (a test that fails only then is a flaky test, issue 22).
LOAD_CPUS ?= 2
test-loaded: test-deps install-test stress-ng
	@stress-ng --cpu $(LOAD_CPUS) --timeout 0 --quiet & load=$$!; \
	  trap 'kill $$load 2>/dev/null; wait $$load 2>/dev/null' EXIT INT TERM; \
	  echo "stress-ng --cpu $(LOAD_CPUS) (pid $$load) beside the suite"; \
	  $(MAKE) --no-print-directory test-run

bench: install-test
	$(BIN)/python bench/kinematics.py

# pypot 5.0.2 and armserver measured by the shared harness in one run (server on CPU 0, load on
# CPU 1), then the issue-12 table as ratios. PEERS: the harness (../shared/peers from the main
# checkout, ../../shared/peers from a worktree); PEERS_OUT: where its figures go.
# PEERS_VENV: pypot's venv and the harness's clients, made from the interpreter the project's venv
# is made from (PYTHON), so that both servers run the same Python build.
PEERS     ?= $(firstword $(wildcard ../shared/peers ../../shared/peers))
PEERS_OUT ?= /tmp/peers-out
PEERS_VENV ?= $(HOME)/.cache/armserver-peers/venv-$(subst /,-,$(patsubst /%,%,$(PYTHON)))
export PEERS_VENV
bench-peers: install-test
	@test -n "$(PEERS)" || { echo "no ../shared/peers harness found (set PEERS=)"; exit 2; }
	test -x $(PEERS_VENV)/bin/python || { $(PYTHON) -m venv $(PEERS_VENV) \
	  && $(PEERS_VENV)/bin/python -m pip install --quiet -r $(PEERS)/requirements.lock; }
	rm -rf $(PEERS_OUT)
	-DUR=$${DUR:-8} $(PEERS)/run.sh $(PEERS_OUT)
	$(BIN)/python bench/peers.py $(PEERS_OUT) --harness $(PEERS)

# A lab on one PC (issue 27): ARMS simulated rbe3001 arms on socket:// links, WORKERS worker
# processes behind one address (unpinned: the workers are there to use every core; --pin puts
# the server on CPU 0 as issue 27's one-process table was measured).
ARMS    ?= 4
WORKERS ?= 2
bench-lab: install-test
	$(BIN)/python bench/lab.py --arms $(ARMS) --workers $(WORKERS)

fuzz: install-test
	ARMSERVER_FUZZ_CASES=300 $(BIN)/python -m pytest -q tests/test_fuzz_api.py \
	  tests/test_fuzz_hostile.py tests/test_fuzz_dynamixel.py tests/test_fuzz_rbe3001.py
	@cat test-output/fuzz-report.txt

soak: install-test
	$(BIN)/python bench/soak.py --seconds 300

# A dataset recorded by armserver loaded by lerobot's own LeRobotDataset (issue 26): lerobot in
# its own venv (it brings torch, several GB: not part of `make test`), tools/check_lerobot.py
# records (a kill -9 mid-episode and a restart included) and compares every frame.
LEROBOT_VENV ?= .venv-lerobot
LEROBOT_OUT  ?= /tmp/armserver-check-lerobot
$(LEROBOT_VENV)/.installed:
	$(PYTHON) -m venv $(LEROBOT_VENV)
	$(LEROBOT_VENV)/bin/python -m pip install --quiet lerobot
	touch $@

check-lerobot: install $(LEROBOT_VENV)/.installed
	rm -rf $(LEROBOT_OUT)
	$(BIN)/python tools/check_lerobot.py record $(LEROBOT_OUT)
	$(LEROBOT_VENV)/bin/python tools/check_lerobot.py load $(LEROBOT_OUT)/recordings/check

lint: install-test
	$(BIN)/python -m pip install --quiet ruff mypy
	$(BIN)/ruff check protocol kinematics app tests bench examples
	$(BIN)/mypy --strict protocol kinematics app
	$(BIN)/python tools/check_cycles.py app
	$(BIN)/python tools/check_cycles.py --types app

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
