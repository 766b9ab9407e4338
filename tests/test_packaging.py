"""The wheel carries what an installed armfusion needs: every module of the three layers
and the shipped configs as package data (``config/`` as ``armfusion.config``), and an
unpacked wheel finds them from any directory.

Built offline (``--no-build-isolation``: setuptools and wheel come from the test extras)
from a copy of the sources in tmp_path, so no ``build/`` folder of the working tree (whose
stale files setuptools would pack) is read or written.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("sensors", "models", "fusion")
API = "armfusion"  # the folder of the user-facing API; the layers install below it


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for folder in (API, *LAYERS, "config"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "--no-index", "-w", str(out), str(src)],
        check=True, capture_output=True, timeout=120)
    (whl,) = out.glob("armfusion-*.whl")
    return whl


def test_the_wheel_carries_every_shipped_config_byte_for_byte(wheel):
    shipped = sorted(p for p in (ROOT / "config").rglob("*") if p.is_file())
    assert {p.name for p in shipped} >= {"wmra.yaml", "crs_a465.yaml", "zenoh.json5", "chair.json5",
                                         "imu-rig.yaml", "broad.yaml"}  # the last two: imports/
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        for p in shipped:
            member = "armfusion/config/" + p.relative_to(ROOT / "config").as_posix()
            assert member in names, f"{member} missing from the wheel"
            assert z.read(member) == p.read_bytes()
    assert not [n for n in names if n.startswith("armfusion/config/") and n.endswith(".py")]


def test_the_wheel_carries_every_module_of_the_layers_and_no_tests_or_tools(wheel):
    sources = {f"{API}/{p.relative_to(ROOT).as_posix()}" for layer in LAYERS for p in (ROOT / layer).rglob("*.py")}
    sources.add(f"{API}/__init__.py")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        entry_points = next(z.read(n).decode() for n in names if n.endswith("entry_points.txt"))
    missing = sorted(sources - names)
    assert not missing, f"not in the wheel (a sub-package missing from pyproject's packages?): {missing}"
    assert not [n for n in names if n.split("/")[0] in ("tests", "tools", "config")]
    assert "armfusion = armfusion.fusion.cli.main:app" in entry_points


def test_an_unpacked_wheel_finds_its_configs_from_another_directory(wheel, tmp_path):
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    probe = ("from armfusion.fusion.configfile import load_arm, resolve_config_path\n"
             "from armfusion.fusion.service.zenoh_config import DEFAULT_CONFIG_PATH, DEPLOY_CONFIG_DIR\n"
             "print(resolve_config_path('wmra')); print(DEFAULT_CONFIG_PATH)\n"
             "print(DEPLOY_CONFIG_DIR / 'chair.json5'); print(len(load_arm('crs_a465').joints))\n"
             "from armfusion.fusion.importing.column_map import load_column_map\n"
             "print(load_column_map('imu-rig').source)\n")
    # the unpacked wheel first on the path: it, not the working tree, provides the packages
    done = subprocess.run([sys.executable, "-c", probe], cwd=elsewhere, capture_output=True, text=True,
                          env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    wmra, zenoh_json5, chair, n_joints, rig_map = done.stdout.split()
    for found in (wmra, zenoh_json5, chair, rig_map):
        assert Path(found).is_file() and Path(found).is_relative_to(site), found
    assert Path(wmra).name == "wmra.yaml" and int(n_joints) == 6


def test_the_api_pages_python_example_runs_as_written(tmp_path):
    """The Python API page's example: what a user's code imports, run from elsewhere."""
    page = (ROOT / "docs" / "reference" / "api.md").read_text()
    section = page
    start = section.index("```python\n") + len("```python\n")
    code = section[start:section.index("\n```", start)]
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert [line.split()[0] for line in lines[:7]] == [f"j{k}" for k in range(1, 8)]
    assert "'steps':" in lines[7] and (tmp_path / "poses.csv").is_file()


def test_unrelated_models_and_sensors_packages_are_left_alone(wheel, tmp_path):
    """A user's environment that already has top-level ``models`` and ``sensors`` packages (a
    web app, a training repo): installing armfusion shadows neither, and armfusion still runs
    from another directory, its commands included."""
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    theirs = tmp_path / "theirs"
    for name in ("models", "sensors", "fusion"):
        (theirs / name).mkdir(parents=True)
        (theirs / name / "__init__.py").write_text(f"OWNER = 'theirs: {name}'\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    probe = ("import models, sensors, fusion, armfusion\n"
             "print(models.OWNER, sensors.OWNER, fusion.OWNER, sep='|')\n"
             "arm = armfusion.load_arm('wmra'); print(len(arm.joints))\n"
             "import sys; sys.argv = ['armfusion', 'info', '--config', 'wmra']\n"
             "from armfusion.fusion.cli.main import app\n"
             "app()\n")
    # theirs first on the path, as an environment that had them before armfusion came
    env = {"PYTHONPATH": f"{theirs}:{site}", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", probe], cwd=elsewhere, capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    first, n_joints, *info = done.stdout.splitlines()
    assert first == "theirs: models|theirs: sensors|theirs: fusion"
    assert int(n_joints) == 7
    assert any("j7" in line for line in info), done.stdout[-2000:]
