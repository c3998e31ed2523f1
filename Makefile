# Two commands for a newcomer: `make demo` and `make test`. Each creates .venv when missing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= out

.PHONY: demo test lint format bench clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# out/ is the demo's own folder (`make clean` removes it): a second `make demo` replaces it
demo: $(STAMP)
	$(VENV)/bin/sssjax demo --out $(OUT) --force

# `make test`: everything but the long physics checks marked `slow` (about 10 minutes on
# 2 cores); `make test TESTS=all` (what .ci/run runs) adds them. `--dist loadfile`: the tests
# of one file share compiled programs and results in one worker (pytest 9.2 ignores
# xdist_group marks, pytest-xdist issue 1386). The previewer's browser test needs Debian's
# chromium (CI runs this as root).
TESTS ?= fast
ifeq ($(TESTS),all)
MARK :=
else ifeq ($(TESTS),fast)
MARK := -m "not slow"
else ifeq ($(TESTS),slow)
MARK := -m slow
else
$(error TESTS must be fast, slow or all, got '$(TESTS)')
endif
test: $(STAMP)
	@test -x /usr/bin/chromium || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium)
	$(PY) -m pytest -n 2 --dist loadfile -q --durations=40 $(MARK)

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format . && $(VENV)/bin/ruff check --fix .

bench: $(STAMP)
	$(PY) benchmarks/render.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
