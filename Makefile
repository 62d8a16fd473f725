# NebulaRT: the two commands (both set up everything they need first).
#   make render   trace the default nebula -> out/thesis-default.vti + out/thesis-default.png
#   make test     run the whole test suite on PoCL (OpenCL on the CPU)
VENV ?= .venv
PY := $(VENV)/bin/python
SCENE ?= examples/scenes/thesis-default.toml

.PHONY: setup render test bench clean

setup:
	@bash scripts/setup.sh

render: setup
	@mkdir -p out
	$(VENV)/bin/nebula-rt render $(SCENE) -o out/thesis-default.vti --png out/thesis-default.png

# the suite in TEST_WORKERS processes, each module's tests in one (module fixtures once);
# TEST_WORKERS=0 runs it in this process
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadscope $(PYTEST_ARGS)

bench: setup
	$(PY) benchmarks/bench_transport.py

clean:
	rm -rf out .pytest_cache
