# Two commands do all the set-up on a fresh machine (Python 3.11):
#   make run    create .venv if missing, then run the whole pipeline (snakemake --cores 2)
#   make test   create .venv if missing, then run the tests
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
export PATH := $(CURDIR)/$(VENV)/bin:$(PATH)

.PHONY: run test test-all env clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

env: $(STAMP)

run: $(STAMP)
	snakemake --cores 2

test: $(STAMP)
	pytest -q

clean:
	rm -rf data logs .snakemake reports/*.html
