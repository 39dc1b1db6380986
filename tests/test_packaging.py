"""Packaging: one installed name (trianflow_vo), every package folder listed, presets shipped."""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from conftest import REPO

FOLDERS = {"vo": "trianflow_vo", "models": "trianflow_vo.models", "cli": "trianflow_vo.cli",
           "configs": "trianflow_vo.configs", "train": "trianflow_vo.train"}


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_every_package_folder_is_listed_under_one_installed_name():
    st = _pyproject()["tool"]["setuptools"]
    assert st["package-dir"] == {v: k for k, v in FOLDERS.items()}
    found = set()
    for folder, name in FOLDERS.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder)
            found.add(".".join([name, *rel.parts]))
    assert sorted(found) == sorted(st["packages"]), "pyproject.toml [tool.setuptools] packages is out of date"
    assert all(p.startswith("trianflow_vo") for p in st["packages"])


def test_console_script_points_into_the_namespace():
    assert _pyproject()["project"]["scripts"] == {"trianflow-vo": "trianflow_vo.cli.main:main"}


def test_wheel_installs_no_generic_top_level_package(tmp_path):
    pytest.importorskip("setuptools", reason="building the wheel without isolation needs setuptools")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(REPO),
                          "-w", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    (wheel,) = tmp_path.glob("*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"trianflow_vo", wheel.name.split("-")[0] + "-" + wheel.name.split("-")[1] + ".dist-info"}
    for preset in ("default", "kitti", "indoor"):
        assert f"trianflow_vo/configs/{preset}.yaml" in names
    assert "trianflow_vo/models/pwc.py" in names and "trianflow_vo/cli/main.py" in names


def test_help_is_instant_no_heavy_imports():
    code = ("import sys; from click.testing import CliRunner; from trianflow_vo.cli.main import main;"
            "r = CliRunner().invoke(main, ['run', '--help']); assert r.exit_code == 0, r.output;"
            "heavy = [m for m in ('torch', 'onnxruntime', 'rerun', 'evo', 'matplotlib', 'cv2') if m in sys.modules];"
            "print(heavy)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=Path("/"))
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"
