# The two commands of the README: `make demo` and `make test`. Each sets everything up
# (system packages if missing, a virtual environment, the package) and then runs.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup-system.sh
	sh scripts/setup-system.sh "$(PYTHON)"
	"$(PYTHON)" -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[cloud,test]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fleetslam demo

test: $(STAMP)
	$(VENV)/bin/python -m pytest -n 2 --durations=10

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache
