# midas: `make demo` installs everything and records a short simulated session; `make test` runs the suite.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= sessions

.PHONY: install demo test test-slow lint clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev,train]'
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/midas record --simulate --duration 10 --out $(DEMO_OUT) --subject 1 --task suturing --trial 1 \
		--no-tui > $(VENV)/demo-path.txt
	$(BIN)/midas session info "$$(tail -n 1 $(VENV)/demo-path.txt)"
	$(BIN)/midas session verify "$$(tail -n 1 $(VENV)/demo-path.txt)"

# The suite (about 17 minutes on 2 cores); the long checks marked `slow` run with `make test-slow`
# (.ci/run runs both).
test: install
	$(BIN)/python -m pytest -q -rs -m "not slow"

test-slow: install
	$(BIN)/python -m pytest -q -rs -m slow

lint: install
	$(BIN)/ruff check midas_cli tests benchmarks
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache

# Pipelines (tables, gesture experiments) live in mk/*.mk and use $(BIN)/midas.
-include $(wildcard mk/*.mk)
