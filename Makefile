# The two quick-start commands; each sets up .venv on first use.
SHELL  := /bin/bash
PYTHON ?= python3
VENV   ?= .venv
SPP    ?=

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install -q --upgrade pip
	$(VENV)/bin/pip install -q -e ".[test,bench,frames,video]"
	touch $@

.PHONY: setup render test bench
setup: $(VENV)/.installed

render: $(VENV)/.installed
	$(VENV)/bin/lgshape render scenes/cornell.xml -o cornell.exr $(if $(SPP),--spp $(SPP))

# pytest exits 5 when it collected no tests: a failure for this suite. Its
# stderr is also kept in .pytest_cache/lgshape-stderr: where pytest dies of a
# signal, the end of the output repeats what CI's tail would lose (the first
# lines naming Dr.Jit or the fatal error, the lines printed just before
# Python's report (a C library's or C++ runtime's message), and the dying
# thread's frames outside site-packages, as Python's faulthandler printed
# them).
test: $(VENV)/.installed
	@mkdir -p .pytest_cache; err=.pytest_cache/lgshape-stderr; \
	$(VENV)/bin/python -m pytest -q 2> >(tee $$err >&2); rc=$$?; wait $$!; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 1; fi; \
	if [ $$rc -gt 128 ] && [ -f .pytest_cache/lgshape-current-test ]; then \
	  echo "pytest died of signal $$((rc - 128)) in $$(cat .pytest_cache/lgshape-current-test)"; \
	  grep -m 4 -i -E "fatal|critical|drjit|jit_|error|terminate|assert|malloc|free\(" $$err | cut -c1-400; \
	  echo "-- the lines before Python's report:"; \
	  grep -m 1 -B 6 "^Fatal Python error" $$err | head -6 | cut -c1-400; \
	  awk '/^(Current thread|Thread 0x)/{n++} n==1' $$err | grep -v site-packages | head -16; fi; \
	exit $$rc

bench: $(VENV)/.installed
	$(VENV)/bin/lgshape bench --quick --out bench-out
