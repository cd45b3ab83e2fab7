# The README's two commands: `make run` and `make test`. Both create .venv on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= out

.PHONY: run test bench clean

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

# The main job: a simulated station (Modbus table + serial compass, time scale 20) calibrates the
# paper's reference unit over the real protocols, checks it on the table and against the truth.
run: $(VENV)/.installed
	$(VENV)/bin/compasscal demo -o $(OUT)/demo

test: $(VENV)/.installed
	$(PY) -m pytest -q

bench: $(VENV)/.installed
	$(PY) benchmarks/accuracy.py
	$(PY) benchmarks/drivers.py
	$(PY) benchmarks/procedure.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis
