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


def test_the_compose_file_is_the_production_line_topology():
    """docker-compose.yml: PostgreSQL, the API as several processes leaving the stations to their
    workers, one worker per simulated station; every command is one the CLI accepts. `docker compose
    config` checks it as Docker would wherever the compose plugin is installed."""
    import shlex
    import shutil
    import subprocess

    import yaml
    from typer.testing import CliRunner

    from service.cli import app

    root = Path(__file__).resolve().parent.parent
    compose = yaml.safe_load((root / "docker-compose.yml").read_text())
    services = compose["services"]
    url = {s.get("environment", {}).get("COMPASSCAL_DATABASE_URL") for n, s in services.items() if n != "db" and "sim" not in n}
    assert len(url) == 1 and next(iter(url)).startswith("postgresql://")
    api = shlex.split(services["api"]["command"])
    assert api[:2] == ["compasscal", "serve"] and int(api[api.index("--workers") + 1]) > 1
    workers = {n: shlex.split(s["command"]) for n, s in services.items() if s.get("command", "").startswith("compasscal worker")}
    sims = [n for n, s in services.items() if s.get("command", "").startswith("compasscal sim")]
    assert len(workers) == len(sims) == 2
    assert len({w[w.index("--station") + 1] for w in workers.values()}) == 2
    runner = CliRunner()
    for name, s in services.items():
        if "command" in s:
            args = shlex.split(s["command"])[1:]
            r = runner.invoke(app, [args[0], "--help"])
            assert r.exit_code == 0, (name, r.output)
            options = {a.split("=")[0] for a in args[1:] if a.startswith("--")}
            assert all(o in r.output for o in options), (name, options, r.output)
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        r = subprocess.run(["docker", "compose", "-f", str(root / "docker-compose.yml"), "config"], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
