"""The built wheel, installed into a fresh virtual environment outside the repository, works on its own.

The sdist and the wheel are built the way ``python -m build`` builds them (the wheel from the unpacked sdist), so a
file missing from either is missing here too. The virtual environment sees the site-packages of the interpreter
running the tests (the system one in CI, or the user's own virtual environment) for torch, Lightning and the other
dependencies, after its own (nothing is downloaded), and the wheel is installed into it with ``--no-deps``; the test
checks that ``lightning_vtr`` is then imported from the venv's own site-packages, not from the repository (the
development install is an editable one, whose hook the new venv does not load). Every command runs from a temporary
directory outside the repository, without ``PYTHONPATH``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
import yaml

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
#: The package's files that are not Python modules and are read at run time (or by type checkers).
DATA_FILES = (
    "lightning_vtr/py.typed",
    "lightning_vtr/experiments/strategies.yaml",
    "lightning_vtr/cli/help/fit.txt",
    "lightning_vtr/cli/help/validate.txt",
    "lightning_vtr/cli/help/test.txt",
    "lightning_vtr/cli/help/environment.json",
)


def _run(args: list[str | Path], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    done = subprocess.run(
        [str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    assert done.returncode == 0, f"{args} exited {done.returncode}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


def _setuptools_can_build() -> bool:
    """Whether this interpreter's setuptools satisfies [build-system] (>= 77), so no isolated env is needed."""
    if importlib.util.find_spec("setuptools") is None:
        return False
    import setuptools

    return int(setuptools.__version__.split(".")[0]) >= 77


@pytest.fixture(scope="module")
def dist(tmp_path_factory) -> dict[str, Path]:
    """The sdist and the wheel of the working tree, built by ``python -m build`` into a temporary directory."""
    out = tmp_path_factory.mktemp("dist")
    # without a recent enough setuptools here, build's isolated environment fetches one from the index
    isolation = ["--no-isolation"] if _setuptools_can_build() else []
    _run([sys.executable, "-m", "build", "--outdir", out, *isolation, ROOT], cwd=out)
    (wheel,) = out.glob("lightning_vtr-*.whl")
    (sdist,) = out.glob("lightning_vtr-*.tar.gz")
    return {"wheel": wheel, "sdist": sdist}


@pytest.fixture(scope="module")
def venv(dist, tmp_path_factory) -> Path:
    """A virtual environment outside the repository with the wheel installed; returns its ``bin`` directory."""
    root = tmp_path_factory.mktemp("venv")
    assert ROOT not in root.resolve().parents
    _run([sys.executable, "-m", "venv", root / "env"], cwd=root)
    bin_dir = root / "env" / ("Scripts" if os.name == "nt" else "bin")
    venv_site = Path(_run([bin_dir / "python", "-c", _PURELIB], cwd=root).stdout.strip())
    # The running interpreter's package folders, after the venv's own: a path line in a .pth file adds the folder
    # without running the .pth files inside it, so the editable install's import hook stays behind.
    (venv_site / "_test_wheel_running_interpreter.pth").write_text(
        "".join(f"{folder}\n" for folder in _package_folders()), encoding="utf-8"
    )
    _run([bin_dir / "python", "-m", "pip", "install", "--no-deps", "--no-index", dist["wheel"]], cwd=root)
    return bin_dir


_PURELIB = "import sysconfig; print(sysconfig.get_paths()['purelib'])"


def _package_folders() -> list[str]:
    """The site-packages folders of the interpreter running the tests (a venv's, the system's or both)."""
    folders = [
        entry
        for entry in sys.path
        if Path(entry).name in ("site-packages", "dist-packages") and Path(entry).is_dir() and Path(entry) != ROOT
    ]
    assert folders, f"no site-packages folder on sys.path: {sys.path}"
    return folders


def test_wheel_and_sdist_carry_the_data_files(dist):
    wheel_names = set(zipfile.ZipFile(dist["wheel"]).namelist())
    assert set(DATA_FILES) <= wheel_names
    with tarfile.open(dist["sdist"]) as sdist:
        sdist_names = {name.split("/", 1)[1] for name in sdist.getnames() if "/" in name}
    assert set(DATA_FILES) <= sdist_names
    assert {"README.md", "LICENSE", "examples/quickstart.py", "tests/conftest.py"} <= sdist_names
    # the research folder beside the package (research/) is in neither
    assert (ROOT / "research" / "scores.py").is_file()
    assert [n for n in wheel_names if n.split("/", 1)[0] == "research"] == []
    assert [n for n in sdist_names if n.split("/", 1)[0] == "research"] == []
    # every module of the working tree is in the wheel, and nothing else of the package
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "lightning_vtr").rglob("*.py")}
    assert {n for n in wheel_names if n.startswith("lightning_vtr/") and n.endswith(".py")} == modules
    metadata = next(n for n in wheel_names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(dist["wheel"]).read(metadata).decode()
    assert "License-Expression: Apache-2.0" in text
    assert "Classifier: Typing :: Typed" in text


def test_installed_wheel_runs_outside_the_repository(venv, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    site = _run(
        [
            venv / "python",
            "-c",
            "import importlib.resources, lightning_vtr, sysconfig; print(lightning_vtr.__file__); "
            "print(sysconfig.get_paths()['purelib']); "
            "print(importlib.resources.files('lightning_vtr').joinpath('py.typed').is_file())",
        ],
        cwd=work,
    ).stdout.splitlines()
    package_file, purelib, typed = Path(site[0]).resolve(), Path(site[1]).resolve(), site[2]
    assert package_file == purelib / "lightning_vtr" / "__init__.py"
    assert ROOT not in package_file.parents
    assert typed == "True"

    # the console script lists every sub-command
    help_text = _run([venv / "lightning-vtr", "--help"], cwd=work).stdout
    for command in ("build-dataset", "dataset-info", "report", "predict", "pix3d", "evaluate-folder"):
        assert re.search(rf"^\s+{re.escape(command)}\b", help_text, re.MULTILINE), help_text

    # the strategies are read from the shipped strategies.yaml: one line per row, in the file's order
    listed = _run([venv / "lightning-vtr", "report", "--list-strategies"], cwd=work).stdout.splitlines()
    rows = yaml.safe_load((ROOT / "lightning_vtr" / "experiments" / "strategies.yaml").read_text(encoding="utf-8"))
    assert [line.split(":", 1)[0] for line in listed] == list(rows)
    assert listed[0] == f"none: {rows['none']['title']} - {rows['none']['description']}"

    # the quick start (examples/quickstart.py as shipped in the repository) on a tiny dataset built by the wheel's CLI
    _run(
        [
            venv / "lightning-vtr",
            "build-dataset",
            work / "data",
            "--categories",
            "chair,table",
            "--objects-per-category",
            "5",
            "--image-size",
            "64",
            "--views-per-set",
            "3",
            "--no-progress",
        ],
        cwd=work,
    )
    shutil.copy(ROOT / "examples" / "quickstart.py", work / "quickstart.py")
    run_it = "import json, quickstart; print('RESULTS', json.dumps(quickstart.main('data')))"
    printed = _run([venv / "python", "-c", run_it], cwd=work).stdout.splitlines()
    # Two selections (before epoch 0 and after it) of 5 % of the 8 training objects: at least one object each.
    assert "generated samples: 2" in printed
    results = json.loads(next(line for line in printed if line.startswith("RESULTS "))[len("RESULTS ") :])
    metrics = {key: value for output in results for key, value in output.items()}
    for view_set in ("aligned", "hemispherical", "spherical"):
        for metric in ("iou@0.4", "fscore"):
            assert 0.0 <= metrics[f"test/{view_set}/{metric}"] <= 1.0
    assert (work / "lightning_logs").is_dir()  # the Trainer wrote into the temporary working directory
