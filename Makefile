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

# Until the simulated station exists: simulate the paper's reference unit on an ideal table,
# calibrate it from that recording and print the tables.
run: $(VENV)/.installed
	mkdir -p $(OUT)
	$(VENV)/bin/compasscal simulate --unit reference --seed 1 --noise 3 -o $(OUT)/reference.csv
	$(VENV)/bin/compasscal fit $(OUT)/reference.csv -o $(OUT)/reference.cal.json --plot $(OUT)/reference.png

test: $(VENV)/.installed
	$(PY) -m pytest -q

bench: $(VENV)/.installed
	$(PY) benchmarks/accuracy.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis
