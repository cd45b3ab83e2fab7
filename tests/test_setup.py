"""Set-up and CI: `make run`'s database, the test client's HTTP library, warnings as errors (issue 15)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def make_run(*args: str) -> str:
    """The command `make run` would run (dry run: nothing is installed or started)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAKE") and k != "MFLAGS"}
    r = subprocess.run(["make", "--no-print-directory", "-n", "run", *args], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip().splitlines()[-1]


def test_make_run_uses_the_home_default_unless_asked():
    line = make_run()
    assert "compasscal demo --api" in line and "COMPASSCAL_DATABASE_URL" not in line


def test_make_run_can_use_a_database_of_the_checkouts_own():
    line = make_run("DB=./compasscal.db")
    assert f"COMPASSCAL_DATABASE_URL='sqlite:///{ROOT / 'compasscal.db'}'" in line and "compasscal demo --api" in line
    url = "postgresql://user:pw@db:5432/compasscal"
    assert f"COMPASSCAL_DATABASE_URL='{url}'" in make_run(f"DB={url}")


def test_a_checkout_database_is_not_committed():
    for name in ("compasscal.db", "compasscal.db-wal", "compasscal.db-shm"):
        assert subprocess.run(["git", "check-ignore", "-q", name], cwd=ROOT).returncode == 0, name


def test_the_test_client_imports_without_a_deprecation():
    """starlette's TestClient wants httpx2 (with plain httpx it warns on import)."""
    r = subprocess.run([sys.executable, "-W", "error", "-c", "import fastapi.testclient"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("module", ["physics.errorsep", "service.cli", "drivers.compass", "procedures.engine", "proof.runner"])
def test_a_warning_from_the_projects_code_fails_the_test(module: str):
    with pytest.raises(RuntimeWarning):
        warnings.warn_explicit("x", RuntimeWarning, module.replace(".", "/") + ".py", 1, module=module)


def test_a_warning_from_a_test_module_fails_the_test():
    with pytest.raises(UserWarning):
        warnings.warn("from a test")


def test_readme_says_how_to_get_the_command_and_choose_the_database():
    readme = (ROOT / "README.md").read_text()
    assert ".venv/bin/compasscal" in readme and "source .venv/bin/activate" in readme
    assert "make run DB=./compasscal.db" in readme
