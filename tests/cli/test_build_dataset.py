"""``lightning-vtr build-dataset``: flags to build options (builds themselves: tests/data/test_builder.py)."""

from __future__ import annotations

import argparse

import pytest

from lightning_vtr.cli import main
from lightning_vtr.cli.build_dataset import add_arguments


@pytest.fixture
def builds(monkeypatch):
    """The arguments of every build_dataset call `lightning-vtr build-dataset` makes (nothing is built)."""
    calls = []

    class Report:
        finalized = False

        def summary(self):
            return "built nothing"

    def fake_build_dataset(output, **kwargs):
        calls.append((output, kwargs))
        return Report()

    monkeypatch.setattr("lightning_vtr.data.builder.build_dataset", fake_build_dataset)
    return calls


def test_layout_and_up_axis_choices_are_the_data_constants():
    from lightning_vtr.data.builder import SOURCE_LAYOUTS
    from lightning_vtr.data.format import UP_AXES

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    choices = {a.dest: a.choices for a in parser._actions}
    assert tuple(choices["layout"]) == SOURCE_LAYOUTS and "generic" in choices["layout"]
    assert tuple(choices["up_axis"]) == tuple(UP_AXES)


def test_options_given_and_defaults(builds, tmp_path, capsys):
    argv = [
        "build-dataset",
        str(tmp_path),
        "--categories",
        "chair,table",
        "--image-size",
        "32",
        "--shard",
        "1/4",
        "--layout",
        "generic",
        "--up-axis",
        "y",
        "--split",
        "0.5,0.25,0.25",
        "--workers",
        "2",
        "--no-progress",
    ]
    assert main(argv) == 0
    output, kwargs = builds[-1]
    assert output == tmp_path
    assert kwargs == {
        "source": "procedural",
        "split": (0.5, 0.25, 0.25),
        "workers": 2,
        "shard": (1, 4),
        "progress": False,
        "source_layout": "generic",
        "up_axis": "y",
        "categories": ["chair", "table"],
        "image_size": 32,
    }
    assert "Shard 1/4 done" in capsys.readouterr().out


def test_embedded_takes_the_embedded_options_for_every_option_not_given(builds, monkeypatch, tmp_path):
    from lightning_vtr.data.builder import EMBEDDED_DEFAULTS

    monkeypatch.setenv("LIGHTNING_VTR_DATA", str(tmp_path))
    assert main(["build-dataset", "--embedded", "--image-size", "32"]) == 0
    output, kwargs = builds[-1]
    assert output.parent == tmp_path and output.name.startswith("embedded-")
    assert {k: kwargs[k] for k in EMBEDDED_DEFAULTS} == {**EMBEDDED_DEFAULTS, "image_size": 32}


def test_errors_print_one_line(builds, capsys, tmp_path):
    assert main(["build-dataset"]) == 2
    assert "OUTPUT is required unless --embedded" in capsys.readouterr().err
    assert main(["build-dataset", str(tmp_path), "--embedded", "--source", str(tmp_path)]) == 2
    assert "--embedded builds the procedural source" in capsys.readouterr().err
    assert main(["build-dataset", str(tmp_path), "--layout", "shapenet_v3"]) == 2
    assert "invalid choice: 'shapenet_v3'" in capsys.readouterr().err
    assert builds == []


# ------------------------------------------------------------------------------------------ end to end


def test_cli_build_and_info(tmp_path, capsys):
    out = tmp_path / "cli"
    args = [
        "build-dataset",
        str(out),
        "--categories",
        "bench",
        "--objects-per-category",
        "2",
        "--image-size",
        "16",
        "--views-per-set",
        "2",
        "--no-progress",
    ]
    assert main(args) == 0
    assert "bench" in capsys.readouterr().out
    assert main(["dataset-info", str(out)]) == 0
    line = next(row for row in capsys.readouterr().out.splitlines() if row.split()[:1] == ["bench"])
    assert line.split()[1:] == ["1", "0", "1", "2"]
    assert main(args) == 0 and "skipped 2" in capsys.readouterr().out


def test_cli_errors(tmp_path, capsys):
    assert main(["build-dataset", str(tmp_path), "--shard", "3/2"]) == 2
    assert "0 <= i < n" in capsys.readouterr().err
    assert main(["build-dataset", str(tmp_path), "--source", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["dataset-info", str(tmp_path)]) == 2
    assert "build-dataset" in capsys.readouterr().err
    assert main(["build-dataset", str(tmp_path / "x"), "--finalize"]) == 2
    assert "build_config.json" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ Pix3D protocol


def test_pix3d_protocol_flags_reach_the_builder(builds, tmp_path):
    argv = ["build-dataset", str(tmp_path), "--protocol", "pix3d", "--views-per-object", "60", "--categories", "chair"]
    assert main([*argv, "--pitch-range=-5,35", "--no-progress"]) == 0  # "=": the value starts with "-"
    _, kwargs = builds[-1]
    assert kwargs["protocol"] == "pix3d" and kwargs["views_per_object"] == 60 and kwargs["pitch_range"] == (-5.0, 35.0)
    assert kwargs["categories"] == ["chair"] and "views_per_set" not in kwargs
    assert main(["build-dataset", str(tmp_path), "--no-progress"]) == 0
    assert not {"protocol", "views_per_object", "pitch_range"} & set(builds[-1][1])  # not given: builder defaults


def test_pix3d_flag_errors(builds, capsys, tmp_path):
    for bad in ("40,0", "0", "a,b", "-100,0"):
        assert main(["build-dataset", str(tmp_path), "--protocol", "pix3d", f"--pitch-range={bad}"]) == 2
        assert "--pitch-range" in capsys.readouterr().err
    assert main(["build-dataset", str(tmp_path), "--protocol", "pix2d"]) == 2
    assert "invalid choice: 'pix2d'" in capsys.readouterr().err
    assert builds == []


def test_cli_pix3d_build(tmp_path, capsys):
    out = tmp_path / "pix3d"
    args = ["build-dataset", str(out), "--protocol", "pix3d", "--views-per-object", "3", "--categories", "chair"]
    assert main([*args, "--objects-per-category", "2", "--image-size", "16", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "built 2" in printed and "3 views per set ['pix3d']" in printed
    assert sorted(p.name for p in out.rglob("*.png")) == ["00.png", "00.png", "01.png", "01.png", "02.png", "02.png"]
    assert main(["build-dataset", str(tmp_path / "vtr"), "--views-per-object", "3"]) == 2
    assert "`views_per_object` applies to protocol='pix3d' only" in capsys.readouterr().err
    assert not (tmp_path / "vtr").exists()
