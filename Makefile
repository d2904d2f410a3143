# The two quick-start commands; each sets up .venv on first use.
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

# pytest exits 5 when it collected no tests: a failure for this suite.
test: $(VENV)/.installed
	@$(VENV)/bin/python -m pytest -q; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 1; fi; \
	if [ $$rc -gt 128 ] && [ -f .pytest_cache/lgshape-current-test ]; then \
	  echo "pytest died of signal $$((rc - 128)) in $$(cat .pytest_cache/lgshape-current-test)"; fi; \
	exit $$rc

bench: $(VENV)/.installed
	$(VENV)/bin/lgshape bench --quick --out bench-out
