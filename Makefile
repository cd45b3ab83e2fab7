# The README's two commands: `make run` and `make test`. Both create .venv on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= out
PORT ?= 8000
# The service's database for `make run`. Empty: the user's SQLite default (~/.local/share/compasscal/
# compasscal.db, shared by every checkout). A path gives a SQLite file of its own (DB=./compasscal.db
# for this checkout's), a URL any database (DB=postgresql://user:pw@host:5432/compasscal).
DB ?=
DB_ENV := $(if $(strip $(DB)),COMPASSCAL_DATABASE_URL='$(if $(findstring ://,$(DB)),$(DB),sqlite:///$(abspath $(DB)))')

.PHONY: run demo test bench clean

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

# The main job: a simulated station (Modbus table + serial compass, time scale 20) and the REST
# service on the SQLite default; an operator key; the paper's reference unit calibrated through the
# API; the database, the result and the URLs printed; then it keeps serving until interrupted (Ctrl-C).
run: $(VENV)/.installed
	$(DB_ENV) $(VENV)/bin/compasscal demo --api --port $(PORT)

# The same calibration without the service (command line only; exits when done).
demo: $(VENV)/.installed
	$(VENV)/bin/compasscal demo -o $(OUT)/demo

# What CI runs: three processes (pytest-xdist; each has its own PostgreSQL database; many tests wait
# on a simulated station's clock, so a third process uses the time a second leaves idle on two cores),
# then the tests marked serial (they stop PostgreSQL) alone. One at a time: .venv/bin/python -m pytest
test: $(VENV)/.installed
	$(PY) -m pytest -q -n 3 -m "not serial"
	$(PY) -m pytest -q -m serial

bench: $(VENV)/.installed
	$(PY) benchmarks/accuracy.py
	$(PY) benchmarks/drivers.py
	$(PY) benchmarks/procedure.py
	$(PY) benchmarks/service_speed.py
	$(PY) benchmarks/real.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis
