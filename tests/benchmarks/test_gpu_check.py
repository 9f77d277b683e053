"""benchmarks/gpu_check.py: rows in child processes, written as they finish, within a budget, never hanging."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
import time
import zipfile
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"


@pytest.fixture(scope="module")
def gpu_check():
    """The script as a module (benchmarks/ is no package); removed from ``sys.modules`` after."""
    spec = importlib.util.spec_from_file_location("gpu_check", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["gpu_check"] = module
    spec.loader.exec_module(module)
    yield module
    for name in [n for n in sys.modules if n == "gpu_check" or n.startswith("_gpu_check_")]:
        del sys.modules[name]


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a killed one no process has reaped yet is a zombie: not running)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "\nState:\tZ" not in status


def _python_row(code: str) -> list[str]:
    """A child command: ``code`` runs with ``out`` (the result path) defined."""
    return [sys.executable, "-c", "import json, sys, time, os\nout = sys.argv[-1]\n" + code]


def _ok(value: float, sleep: float = 0.0) -> list[str]:
    return _python_row(f"time.sleep({sleep}); json.dump({{'setup': 's', 'results': {{'v': {value}}}}}, open(out, 'w'))")


def test_rows_are_written_as_they_finish_and_hangs_and_crashes_are_recorded(gpu_check, tmp_path):
    out = tmp_path / "out"
    pid_file = tmp_path / "grandchild.pid"
    # the second row reads the table the first one left, before the run ends
    peek = _python_row(
        f"md = open({str(out / 'gpu_check.md')!r}).read()\n"
        "json.dump({'results': {'first row in md': float('| first | s | v 1.5 |' in md)}}, open(out, 'w'))"
    )
    hang = _python_row(  # leaves a sleeping grandchild in its process group, then hangs
        "import subprocess\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        f"open({str(pid_file)!r}, 'w').write(str(p.pid))\n"
        "time.sleep(120)"
    )
    specs = [
        gpu_check.RowSpec("first", _ok(1.5), 30),
        gpu_check.RowSpec("peek", peek, 30),
        gpu_check.RowSpec("hang", hang, 3),
        gpu_check.RowSpec("abort", _python_row("print('about to abort', flush=True); os.abort()"), 30),
        gpu_check.RowSpec(
            "raises", _python_row("json.dump({'error': 'RuntimeError: CUDA error: x'}, open(out, 'w'))"), 30
        ),
        gpu_check.RowSpec("last", _ok(2), 30),
    ]
    start = time.perf_counter()
    table = gpu_check.run_table(specs, out, ["caption"], budget_s=120, start=start)
    assert time.perf_counter() - start < 30  # the hung row cost its 3 s timeout (+ the kill grace), no more

    rows = {row.check: row for row in table}
    assert [row.check for row in table] == ["first", "peek", "hang", "abort", "raises", "last"]
    assert rows["first"].results == {"v": 1.5} and rows["first"].error is None
    assert rows["peek"].results == {"first row in md": 1.0}
    assert rows["hang"].error == "no result within 3 s; its processes were killed"
    assert 3 <= rows["hang"].wall_s < 3 + 2 * gpu_check.KILL_GRACE_S
    assert not _running(int(pid_file.read_text()))  # the whole process group went
    assert rows["abort"].error == "its process ended by SIGABRT without a result; last log line: about to abort"
    assert rows["raises"].error == "RuntimeError: CUDA error: x"
    assert rows["last"].results == {"v": 2} and rows["last"].error is None

    lines = (out / "gpu_check.md").read_text().splitlines()
    assert lines[:4] == ["caption", "", "| check | setup | results | wall s |", "| --- | --- | --- | --- |"]
    assert [line.split(" | ")[0].removeprefix("| ") for line in lines[4:]] == [row.check for row in table]
    assert lines[4].startswith("| first | s | v 1.5 | ")
    assert "| abort |  | ERROR: its process ended by SIGABRT" in lines[7]
    records = [json.loads(line) for line in (out / "gpu_check.jsonl").read_text().splitlines()]
    assert records[0]["header"] == ["caption"]
    assert [r["check"] for r in records[1:]] == [row.check for row in table]
    assert (out / "logs" / "abort.log").read_text() == "about to abort\n"


def test_the_budget_stops_the_running_row_and_skips_the_rest_by_name(gpu_check, tmp_path):
    specs = [gpu_check.RowSpec(name, _ok(1, sleep=1.5), 60) for name in ("a", "b", "c", "d")]
    start = time.perf_counter()
    table = gpu_check.run_table(specs, tmp_path, ["caption"], budget_s=2.5, start=start)
    assert time.perf_counter() - start < 2.5 + 2 * gpu_check.KILL_GRACE_S
    assert table[0].results == {"v": 1} and table[0].error is None
    assert table[1].error.startswith("stopped when the budget of 2 s ran out")  # (2.5 printed as 2)
    for row in table[2:]:
        assert row.skipped == "the budget of 2 s was spent before this row" and row.wall_s is None
    text = (tmp_path / "gpu_check.md").read_text()
    assert "| c |  | SKIPPED: the budget of 2 s was spent before this row |  |" in text
    assert "| d |  | SKIPPED: the budget of 2 s was spent before this row |  |" in text


def test_a_failed_renderer_probe_skips_only_the_rendering_rows(gpu_check, tmp_path):
    probe = gpu_check.RowSpec("renderer probe", _python_row("raise SystemExit(3)"), 30)
    specs = [
        gpu_check.RowSpec("plain", _ok(1), 30),
        gpu_check.RowSpec("render 1", _ok(2), 30, needs_renderer=True),
        gpu_check.RowSpec("render 2", _ok(3), 30, needs_renderer=True),
        gpu_check.RowSpec("big", _ok(4), 30, full_size=True),
    ]
    table = gpu_check.run_table(
        specs, tmp_path, ["c"], budget_s=60, start=time.perf_counter(), renderer_probe=probe, refuse_full_size="no GPU"
    )
    assert [row.check for row in table] == ["plain", "renderer probe", "render 1", "render 2", "big"]
    assert table[0].results == {"v": 1}
    assert table[1].error == "its process ended with code 3 without a result"
    reason = "renderer probe failed: its process ended with code 3 without a result"
    assert table[2].skipped == table[3].skipped == reason
    assert table[4].skipped == "no GPU"


def test_without_the_renderer_a_row_runs_its_replacement_or_is_skipped_with_the_hint(gpu_check, tmp_path):
    failing = gpu_check.RowSpec("renderer probe", _python_row("raise SystemExit(3)"), 30)
    specs = [
        gpu_check.RowSpec(
            "fit (render)",
            _ok(1),
            30,
            needs_renderer=True,
            without_renderer=gpu_check.RowSpec("fit (zero123)", _ok(2), 30),
        ),
        gpu_check.RowSpec("render only", _ok(3), 30, needs_renderer=True, without_renderer_hint="; pass --dataset"),
    ]
    table = gpu_check.run_table(
        specs, tmp_path / "a", ["c"], budget_s=60, start=time.perf_counter(), renderer_probe=failing
    )
    assert [row.check for row in table] == ["renderer probe", "fit (zero123)", "render only"]
    assert table[1].results == {"v": 2} and table[1].error is None
    assert table[2].skipped == "renderer probe failed: its process ended with code 3 without a result; pass --dataset"

    # --no-render: the probe never runs (it would succeed here), the same replacement runs
    working = gpu_check.RowSpec("renderer probe", _ok(9), 30)
    table = gpu_check.run_table(
        specs, tmp_path / "b", ["c"], budget_s=60, start=time.perf_counter(), renderer_probe=working, renderer_off="off"
    )
    assert [(row.check, row.skipped) for row in table] == [
        ("renderer probe", "off"),
        ("fit (zero123)", None),
        ("render only", "off; pass --dataset"),
    ]
    assert table[1].results == {"v": 2}
    assert sorted(p.name for p in (tmp_path / "b" / "logs").iterdir()) == ["fit_zero123.log"]

    # a working renderer: the rows themselves run
    table = gpu_check.run_table(
        specs, tmp_path / "c", ["c"], budget_s=60, start=time.perf_counter(), renderer_probe=working
    )
    assert [(row.check, row.results) for row in table] == [
        ("renderer probe", {"v": 9}),
        ("fit (render)", {"v": 1}),
        ("render only", {"v": 3}),
    ]


def test_a_fit_row_without_a_dataset_is_skipped_with_the_hint_when_rendering_is_off(gpu_check, tmp_path):
    code = gpu_check.main(
        ["--tiny", "--device", "cpu", "--no-render", "--out", str(tmp_path), "--rows", "fit: LRGT tiny + callback"]
    )
    assert code == 1
    records = [json.loads(line) for line in (tmp_path / "gpu_check.jsonl").read_text().splitlines()]
    assert [(r["check"], r["skipped"]) for r in records[1:]] == [
        ("renderer probe", "--no-render: the fit rows use zero123 tiny (with --dataset) instead of rendering"),
        (
            "fit: LRGT tiny + callback (bf16-mixed, render)",
            "--no-render: the fit rows use zero123 tiny (with --dataset) instead of rendering; without --dataset DIR "
            "(built by --build-dataset DIR) the row renders its dataset",
        ),
    ]
    with pytest.raises(SystemExit):
        gpu_check.main(["--tiny", "--out", str(tmp_path), "--dataset", str(tmp_path / "none")])


def test_full_size_rows_are_refused_on_a_cpu(gpu_check, tmp_path):
    code = gpu_check.main(["--device", "cpu", "--out", str(tmp_path), "--rows", "zero123,selection: paper"])
    assert code == 1
    records = [json.loads(line) for line in (tmp_path / "gpu_check.jsonl").read_text().splitlines()]
    assert records[0]["environment"]["python"] == ".".join(map(str, sys.version_info[:3]))
    assert [(r["check"], r["skipped"]) for r in records[1:]] == [
        ("zero123", "full-size row refused on a CPU (no CUDA device, or --device cpu); --tiny runs the small rows"),
        ("selection: paper", records[1]["skipped"]),
    ]
    assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == ["environment.log"]  # no row ran


def _wheel(folder: Path, name: str, version: str, requires: list[str]) -> Path:
    path = folder / f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as archive:
        info = f"{name}-{version}.dist-info"
        meta = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}"]
        archive.writestr(f"{info}/METADATA", "\n".join([*meta, *(f"Requires-Dist: {r}" for r in requires)]) + "\n")
        archive.writestr(
            f"{info}/WHEEL", "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
        )
        archive.writestr(f"{name}/__init__.py", f"VERSION = {version!r}\n")
        archive.writestr(f"{info}/RECORD", "")
    return path


def test_choose_wheels_takes_the_newest_whose_requirements_the_installed_packages_meet(gpu_check, tmp_path):
    new = _wheel(tmp_path, "diffusers", "0.42.1", ["huggingface-hub<3.0,>=1.32.0", 'torch>=9; extra == "torch"'])
    old = _wheel(tmp_path, "diffusers", "0.37.1", ["huggingface-hub<2.0,>=0.34.0", "absent-project>=5"])
    other = _wheel(tmp_path, "trimesh", "5.2.0", ["numpy>=1.21"])
    for hub, expected in (("2.4.0", new), ("1.40.0", new), ("1.2.0", old), ("0.20.0", new)):
        versions = {"huggingface-hub": hub, "numpy": "2.0", "torch": "2.11"}
        chosen, notes = gpu_check.choose_wheels([old, other, new], versions.get)
        assert chosen == [expected, other], hub
        assert notes[0].startswith(f"diffusers: {expected.name}")
    # 0.20.0 meets neither: the newest is taken, and the note names what each one lacked
    assert "huggingface-hub<2.0,>=0.34.0 (installed 0.20.0)" in notes[0]


def test_install_wheels_puts_the_chosen_ones_in_site(gpu_check, tmp_path):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    _wheel(wheels, "zzprobe", "2.0", ["zz-not-installed>=1"])
    _wheel(wheels, "zzprobe", "1.0", [])
    site = tmp_path / "site"
    notes = gpu_check.install_wheels(wheels, site, tmp_path / "pip.log")
    assert notes == ["zzprobe: zzprobe-2.0-py3-none-any.whl", "installed: zzprobe-2.0-py3-none-any.whl"]
    assert (site / "zzprobe" / "__init__.py").read_text() == "VERSION = '2.0'\n"
    with pytest.raises(FileNotFoundError, match="no .whl file there"):
        gpu_check.install_wheels(tmp_path / "site", site, tmp_path / "pip.log")


@pytest.mark.slow
def test_tiny_cpu_run_writes_real_rows(gpu_check, tmp_path, capsys):
    rows = "train: LRGT bf16-mixed,selection: visible"
    code = gpu_check.main(["--tiny", "--device", "cpu", "--out", str(tmp_path), "--rows", rows, "--budget-s", "300"])
    printed = capsys.readouterr().out
    assert code == 0, (tmp_path / "gpu_check.md").read_text()
    records = [json.loads(line) for line in (tmp_path / "gpu_check.jsonl").read_text().splitlines()]
    header, table = records[0], records[1:]
    assert header["header"][0].startswith("gpu_check --tiny on CPU")
    assert [r["check"] for r in table] == ["train: LRGT bf16-mixed", "selection: visible"]
    for r in table:
        assert r["error"] is None and r["skipped"] is None and r["wall_s"] > 0
        for name, value in r["results"].items():
            assert math.isfinite(value) and value > 0, (r["check"], name, value)
    train, selection = (r["results"] for r in table)
    assert 0 < train["loss"] < 5 and "bf16-mixed, batch 1" in table[0]["setup"]
    assert selection["best objects/s"] >= selection["objects/s"]
    assert printed.strip().splitlines()[-2].startswith("| train: LRGT bf16-mixed | cpu, tiny preset")
    assert printed.rstrip().endswith((tmp_path / "gpu_check.md").read_text().rstrip())


@pytest.mark.slow
def test_tiny_fit_row_without_opengl_runs_zero123_and_never_imports_pyrender(gpu_check, tmp_path):
    # pyrender, OpenGL and pyglet that fail to import, as on a machine without libGL / libEGL, and note who tried
    blocked, marker = tmp_path / "blocked", tmp_path / "imports.txt"
    for name in ("pyrender", "OpenGL", "pyglet"):
        (blocked / name).mkdir(parents=True)
        (blocked / name / "__init__.py").write_text(
            f"import sys\nopen({str(marker)!r}, 'a').write({name!r} + ' ' + ' '.join(sys.argv[1:]) + '\\n')\n"
            f"raise ImportError('Unable to load OpenGL library ({name} blocked by the test)')\n"
        )
    dataset = tmp_path / "data"
    assert gpu_check.main(["--tiny", "--build-dataset", str(dataset)]) == 0  # built here, where rendering works
    out = tmp_path / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PYTHONPATH", str(blocked))
        code = gpu_check.main(
            [
                "--tiny",
                "--device",
                "cpu",
                "--dataset",
                str(dataset),
                "--out",
                str(out),
                "--rows",
                "fit: LRGT tiny + callback",
            ]
        )
    records = [json.loads(line) for line in (out / "gpu_check.jsonl").read_text().splitlines()]
    probe, fit = records[1:]
    assert probe["check"] == "renderer probe" and "Unable to load OpenGL library" in probe["error"]
    assert code == 1  # the failed probe counts as an error
    assert fit["check"] == "fit: LRGT tiny + callback (bf16-mixed, zero123 tiny)", fit
    assert fit["error"] is None, fit["error"]
    assert "Zero-1-to-3 tiny random weights 64 px, float32, 2 DDIM steps, 32 px dataset" in fit["setup"]
    results = fit["results"]
    assert results["train objects"] == 6  # 2 categories x 5 objects split 3/1/1
    assert results["generated samples"] == 2 * round(gpu_check.FIT_FRACTION * 6)
    assert math.isfinite(results["final loss"]) and results["final loss"] > 0
    tried = marker.read_text().splitlines()
    assert tried and all("--child-row" not in line for line in tried), tried  # the probe and report only
    assert any("--child-renderer" in line for line in tried), tried
