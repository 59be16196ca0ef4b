# Two commands do all the set-up on a fresh machine (Python 3.11):
#   make run    create .venv if missing, then run the whole pipeline (snakemake --cores 2)
#   make test   create .venv if missing, install Debian's chromium for the report's browser test and the
#               test cluster's SLURM, MariaDB, munge and sshd if missing (apt-get, as root or through sudo), then
#               run the tests
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
export PATH := $(CURDIR)/$(VENV)/bin:$(PATH)

.PHONY: run test test-fast env browser cluster clean

# The environment takes about 2.4 GB (torch 0.75 GB); pip's cache is left out so that downloads are not kept a second time.
$(STAMP): pyproject.toml constraints.txt
	@free_mb=$$(df -Pm . | awk 'NR == 2 {print $$4}'); [ "$${free_mb:-0}" -ge 3000 ] || \
	  echo "warning: $(CURDIR) has $${free_mb} MB free; $(VENV) needs about 2,400 MB and the install may stop with 'No space left on device'" >&2
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --no-cache-dir -c constraints.txt -e '.[test]'
	touch $(STAMP)

env: $(STAMP)

# The report test opens reports/index.html in headless Chromium (Debian's package, driven by Playwright).
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null \
	  || echo "warning: could not install chromium; the browser test of the report will be skipped"; }

# The cluster tests (tests/test_cluster.py) start a one-node SLURM with accounting (slurmctld, slurmd, slurmdbd on
# MariaDB, munge) and an sshd for the DVC remote, all as root under a temporary folder (Debian's packages).
CLUSTER_PACKAGES := slurm-wlm slurmdbd munge mariadb-server openssh-server
cluster:
	@for program in slurmctld slurmd slurmdbd munged mariadbd sshd; do \
	  command -v $$program >/dev/null 2>&1 || [ -x /usr/sbin/$$program ] || missing=1; done; \
	[ -z "$$missing" ] || { \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends \
	    $(CLUSTER_PACKAGES) >/dev/null \
	  || echo "warning: could not install $(CLUSTER_PACKAGES); the cluster tests will be skipped"; }

run: $(STAMP)
	snakemake --cores 2

# --durations: the slowest tests close the log, so that a CI run shows where its time went.
# -n 2: two test workers (pytest-xdist), one file at a time each, in the order tests/conftest.py gives
test: $(STAMP) browser cluster
	pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=25

# the fast tier for development: neither the end-to-end workflow runs nor the slow unit tests
test-fast: $(STAMP)
	pytest -q -m "not e2e and not slow"

# every generated artefact, nothing else: run outputs, checkpoints, study work, run state; reports/ keeps its README
clean:
	rm -rf data models checkpoints studies_work logs .snakemake .vtgen
	find reports -mindepth 1 -maxdepth 1 ! -name README.md -exec rm -rf {} +
