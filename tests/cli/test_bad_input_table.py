"""Every row of ``docs/bad_input.md``: a bad input to a ``lightning-vtr`` sub-command, run through
``lightning_vtr.cli.main`` as a user would, answers with its one line and exit status (2: the command line,
1: the data or the system), prints no traceback and leaves nothing behind that looks complete.

The table in the docs is generated from :data:`ROWS` (``python tests/cli/test_bad_input_table.py`` prints it)
and :func:`test_the_docs_table_is_the_tested_one` keeps the two the same.
"""

from __future__ import annotations

import errno
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest


@dataclass
class Row:
    """One bad input: ``argv`` and ``message`` use ``{tmp}`` for the test's folder (``DIR`` in the docs)."""

    command: str
    bad_input: str
    argv: list[str]
    message: str  # the whole line after "lightning-vtr <command>: error: " (argparse: the text after "error: ")
    code: int
    setup: str = ""  # a name in SETUPS
    argparse: bool = False  # an option argparse rejects: the message ends with where --help is
    absent: list[str] = field(default_factory=list)  # paths under {tmp} that must not exist afterwards
    note: str = ""
    inside: str = ""  # a folder under {tmp}: every file the run writes lies in it (no path leaves its root)


_TRUNC = "{tmp}/trunc.ckpt"
_LIGHTNING = "must be a Lightning checkpoint (a file `Trainer.fit` saved), got"
_NO_METADATA = "{tmp}/%s/metadata.json does not exist: {tmp}/%s is not a complete ShapeNet-VTR dataset; build one with `lightning-vtr build-dataset ROOT`."
_OTHER = "must be a new or empty folder or an earlier output (with %s), got '{tmp}/%s' holding 1 other entry (notes.txt); choose another folder"
_CONFIG = "`--config` must be a YAML config of LightningCLI settings (trainer:, model:, data:), got '{tmp}/%s'"
_NOT_A_PICTURE = "`--images`: '{tmp}/views/a.png' must be a PNG, JPEG, WebP or BMP picture, got "
_PERMISSION = "expected a location you may write to, found permission denied"
_FULL = "expected free space on its disk, found the disk full (free space, re-run)"
_IMAGES = ["--images", "{tmp}/views"]
_PREDICT = ["predict", "--ckpt", "{tmp}/good.ckpt", *_IMAGES, "--out", "{tmp}/out"]
_PIX3D = ["pix3d", "--root", "{tmp}/pix3d", "--checkpoint", "{tmp}/good.ckpt", "--out", "{tmp}/out"]
_FOLDER = ["evaluate-folder", "--images", "{tmp}/views", "--voxels", "{tmp}/views", "--checkpoint", "{tmp}/good.ckpt"]
_FIT = ["fit", "--config"]
_ROBUST = ["robustness", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/nowhere", "--out", "{tmp}/out"]

_RULE = __import__("lightning_vtr.utils.paths").utils.paths.RULES
_UNSAFE_DATA = ["predict", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/data", "--out", "{tmp}/out"]
_KEY = "object key %r: "
_LEADS_OUT = (
    "{tmp}/%s: expected a path inside {tmp}/%s, found one that resolves to {tmp}/elsewhere (a name "
    "with '..', an absolute name or a symlink that leads out); nothing was written there"
)
#: metadata.json cases, one per rule of a plain name: case -> (bad input, message after the file name).
_UNSAFE_KEYS = {
    "dot": ("object key with `..`", _KEY % "chair/../../../outside/evil" + _RULE["dot"] + " (its part '..')"),
    "absolute": ("object key absolute", _KEY % "/abs/evil" + _RULE["absolute"]),
    "key": ("object key without `/`", _KEY % "evil" + _RULE["key"] + " (found 0)"),
    "separator": ("object key with `\\`", _KEY % "chair/a\\b" + _RULE["separator"]
                  + " (its object id 'a\\\\b', found '\\\\' at index 1)"),
    "control": ("object key with a control character", _KEY % "chair/a\x07" + _RULE["control"]
                + " (its object id 'a\\x07', found '\\x07' at index 1)"),
    "dash": ("object id `-rf`", _KEY % "chair/-rf" + _RULE["dash"] + " (its object id '-rf')"),
    "empty": ("object id empty", _KEY % "chair/" + _RULE["empty"] + " (its object id '')"),
    "case": ("categories `chair` and `Chair`", _KEY % "Chair/b" + _RULE["case"] + " (its category 'Chair' against "
             "'chair/a')"),
    "nfd": ("object ids `café` written NFC and NFD", _KEY % "chair/cafe\u0301" + _RULE["case"] + " (it against "
            "'chair/caf\u00e9')"),
    "view_set": ("view set `../aligned`", "view set '../aligned': " + _RULE["separator"] + " (found '/' at index 2)"),
}  # fmt: skip
_UNSAFE_OBJECTS = {
    "dot": ["chair/../../../outside/evil"],
    "absolute": ["/abs/evil"],
    "key": ["evil"],
    "separator": ["chair/a\\b"],
    "control": ["chair/a\x07"],
    "dash": ["chair/-rf"],
    "empty": ["chair/"],
    "case": ["chair/a", "Chair/b"],
    "nfd": ["chair/caf\u00e9", "chair/cafe\u0301"],
    "view_set": ["chair/a"],
}

ROWS: list[Row] = [
    # ------------------------------------------------------------------ build-dataset
    Row("build-dataset", "OUTPUT holds other files", ["build-dataset", "{tmp}/other", "--no-progress"],
        "the output folder must be new, empty or an earlier build (with build_config.json), got '{tmp}/other' "
        "holding 1 other entry (notes.txt); choose another folder", 2, "other", absent=["other/build_config.json"]),
    Row("build-dataset", "OUTPUT is a file", ["build-dataset", "{tmp}/notes.txt"],
        "the output folder must be a folder (new, empty or an earlier build), got '{tmp}/notes.txt' (a file)", 2),
    Row("build-dataset", "OUTPUT read-only (a refused write)", ["build-dataset", "{tmp}/new", "--no-progress"],
        f"cannot write '{{tmp}}/new/build_config.json': {_PERMISSION}", 1, "refuse_build",
        absent=["new/build_config.json", "new/metadata.json"]),
    Row("build-dataset", "disk full (a failing write)", ["build-dataset", "{tmp}/new", "--no-progress"],
        f"cannot write '{{tmp}}/new/build_config.json': {_FULL}", 1, "full_build",
        absent=["new/build_config.json", "new/metadata.json"]),
    Row("build-dataset", "`--source` missing", ["build-dataset", "{tmp}/new", "--source", "{tmp}/nowhere"],
        "`source` must be 'procedural' or an existing directory, got '{tmp}/nowhere'", 2),
    Row("build-dataset", "`--objects-per-category 0`", ["build-dataset", "{tmp}/new", "--objects-per-category", "0"],
        "argument --objects-per-category: expected a positive integer, got '0'", 2, argparse=True),
    Row("build-dataset", "`--shard 3/2`", ["build-dataset", "{tmp}/new", "--shard", "3/2"],
        "argument --shard: shard index must satisfy 0 <= i < n, got 3/2", 2, argparse=True),
    Row("build-dataset", "`--pitch-range 50,10`", ["build-dataset", "{tmp}/new", "--pitch-range", "50,10"],
        "argument --pitch-range: expected -90 <= low <= high <= 90, got '50,10'", 2, argparse=True),
    # ------------------------------------------------------------------ dataset-info
    Row("dataset-info", "ROOT missing", ["dataset-info", "{tmp}/nowhere"], _NO_METADATA % ("nowhere", "nowhere"), 2),
    Row("dataset-info", "ROOT a folder of other files", ["dataset-info", "{tmp}/other"],
        _NO_METADATA % ("other", "other"), 2, "other"),
    Row("dataset-info", "`metadata.json` empty", ["dataset-info", "{tmp}/data", "--verify"],
        "{tmp}/data/metadata.json is not valid JSON: Expecting value: line 1 column 1 (char 0)", 1, "empty_meta"),
    Row("dataset-info", "`metadata.json` truncated", ["dataset-info", "{tmp}/data"],
        "{tmp}/data/metadata.json is not valid JSON: Unterminated string starting at: line 1 column 12 (char 11)",
        1, "truncated_meta"),
    Row("dataset-info", "`metadata.json` of another format", ["dataset-info", "{tmp}/data"],
        "{tmp}/data/metadata.json: format is 'pix2vox', expected 'lightning_vtr.shapenet_vtr'", 1, "other_meta"),
    Row("dataset-info", "`--workers 0`", ["dataset-info", "{tmp}/data", "--workers", "0"],
        "argument --workers: expected a positive integer, got '0'", 2, argparse=True),
    # ------------------------------------------------------------------ predict
    Row("predict", "`--ckpt` missing", ["predict", "--ckpt", "{tmp}/none.ckpt", *_IMAGES, "--out", "{tmp}/out"],
        "`--ckpt` must be a checkpoint file, got '{tmp}/none.ckpt' (no such file)", 2, "views", absent=["out"]),
    Row("predict", "`--ckpt` a folder", ["predict", "--ckpt", "{tmp}/views", *_IMAGES, "--out", "{tmp}/out"],
        "`--ckpt` must be a checkpoint file, got '{tmp}/views' (a folder)", 2, "views", absent=["out"]),
    Row("predict", "`--ckpt` empty", ["predict", "--ckpt", "{tmp}/empty.ckpt", *_IMAGES, "--out", "{tmp}/out"],
        f"`--ckpt` {_LIGHTNING} '{{tmp}}/empty.ckpt': an empty file (0 bytes)", 1, "views", absent=["out"]),
    Row("predict", "`--ckpt` truncated (first 5,000 bytes)", ["predict", "--ckpt", _TRUNC, *_IMAGES, "--out", "{tmp}/out"],
        f"`--ckpt` {_LIGHTNING} '{_TRUNC}': 5000 bytes torch cannot read (a truncated copy, or not a torch file)",
        1, "views", absent=["out"]),
    Row("predict", "`--ckpt` a text file", ["predict", "--ckpt", "{tmp}/notes.txt", *_IMAGES, "--out", "{tmp}/out"],
        f"`--ckpt` {_LIGHTNING} '{{tmp}}/notes.txt': 13 bytes torch cannot read (a truncated copy, or not a torch "
        "file)", 1, "views", absent=["out"]),
    Row("predict", "`--ckpt` a plain `torch.save` file", ["predict", "--ckpt", "{tmp}/plain.pt", *_IMAGES, "--out", "{tmp}/out"],
        f"`--ckpt` {_LIGHTNING} '{{tmp}}/plain.pt': a plain torch.save file holding a dict of 1 keys without "
        "'state_dict' / 'pytorch-lightning_version'; save models with Trainer.fit / trainer.save_checkpoint",
        1, "views", absent=["out"]),
    Row("predict", "`--ckpt` of the other model class", [*_PREDICT, "--model", "lrgt"],
        "no model class loads the checkpoint '{tmp}/good.ckpt': LRGT: '{tmp}/good.ckpt' is a checkpoint of "
        "Pix2VoxPlusPlus (lightning_vtr.models.pix2vox.Pix2VoxPlusPlus), not of LRGT: LRGT.load_from_checkpoint "
        "cannot load it. Use Pix2VoxPlusPlus.load_from_checkpoint(...) (`lightning-vtr predict --model "
        "lightning_vtr.models.pix2vox.Pix2VoxPlusPlus`).", 1, "views", absent=["out"]),
    Row("predict", "`--images` missing", ["predict", "--ckpt", "{tmp}/good.ckpt", "--images", "{tmp}/nowhere", "--out", "{tmp}/out"],
        "`--images` must name folders of pictures, got '{tmp}/nowhere' (not a folder)", 2, absent=["out"]),
    Row("predict", "`--images` a folder without pictures", ["predict", "--ckpt", "{tmp}/good.ckpt", "--images", "{tmp}/other", "--out", "{tmp}/out"],
        "no pictures in the image folder '{tmp}/other': expected files ending in .png, .jpg, .jpeg, .webp, .bmp "
        "(case-insensitive, masks <stem>_mask.<ext> aside); it holds none", 2, "other", absent=["out"]),
    Row("predict", "`--images` holds `a.png` that is not a picture", _PREDICT,
        _NOT_A_PICTURE + "5 bytes PIL cannot read as a picture (another kind of file)", 1, "not_a_picture", absent=["out"]),
    Row("predict", "`--images` holds a truncated PNG", _PREDICT,
        _NOT_A_PICTURE + "a truncated picture (200 bytes)", 1, "truncated_picture", absent=["out"]),
    Row("predict", "`--images` holds an empty `a.png`", _PREDICT,
        _NOT_A_PICTURE + "an empty file", 1, "empty_picture", absent=["out"]),
    Row("predict", "`--data` missing", ["predict", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/nowhere", "--out", "{tmp}/out"],
        "`--data` must be a ShapeNet-VTR directory or `embedded`, got '{tmp}/nowhere' (no such folder)", 2, absent=["out"]),
    Row("predict", "`--data` a folder of other files", ["predict", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/other", "--out", "{tmp}/out"],
        _NO_METADATA % ("other", "other"), 2, "other", absent=["out"]),
    Row("predict", "`--threshold 1.5`", [*_PREDICT, "--threshold", "1.5"],
        "`--threshold` must be a number in (0, 1), got 1.5", 2, "views", absent=["out"]),
    Row("predict", "`--key-tolerance 300`", [*_PREDICT, "--key-tolerance", "300"],
        "`--key-tolerance` must be in [0, 255], got 300", 2, "views", absent=["out"]),
    Row("predict", "`--batch-size 0`", [*_PREDICT, "--batch-size", "0"],
        "argument --batch-size: expected a positive integer, got '0'", 2, argparse=True),
    Row("predict", "`--out` holds other files", ["predict", "--ckpt", "{tmp}/good.ckpt", *_IMAGES, "--out", "{tmp}/other"],
        "`--out` " + _OTHER % ("predictions.json", "other"), 2, "views_other"),
    Row("predict", "`--out` is a file", ["predict", "--ckpt", "{tmp}/good.ckpt", *_IMAGES, "--out", "{tmp}/notes.txt"],
        "`--out` must be a folder (new, empty or an earlier output), got '{tmp}/notes.txt' (a file)", 2, "views"),
    Row("predict", "`--out` read-only (a refused write)", _PREDICT,
        f"cannot write '{{tmp}}/out/.write-probe': {_PERMISSION}", 1, "refuse_probe", absent=["out"],
        note="checked before the model loads; simulated (a root user's chmod does not refuse writes)"),
    Row("predict", "disk full while exporting", _PREDICT,
        f"cannot write '{{tmp}}/out/views/prediction.binvox': {_FULL}", 1, "full_export",
        absent=["out/predictions.json", "out/index.html"], note="no predictions.json / index.html: not complete"),
    # ------------------------------------------------------------------ report
    Row("report", "`--data` missing", ["report", "--data", "{tmp}/nowhere", "--out", "{tmp}/out"],
        "`--data` must be a ShapeNet-VTR directory or `embedded`, got '{tmp}/nowhere' (no such folder)", 2,
        absent=["out"], note="before Lightning prints anything"),
    Row("report", "`--data` a file", ["report", "--data", "{tmp}/notes.txt", "--out", "{tmp}/out"],
        "`--data` must be a ShapeNet-VTR directory or `embedded`, got '{tmp}/notes.txt' (a file)", 2, absent=["out"]),
    Row("report", "`--data` with a truncated `metadata.json`", ["report", "--data", "{tmp}/data", "--out", "{tmp}/out"],
        "{tmp}/data/metadata.json is not valid JSON: Unterminated string starting at: line 1 column 12 (char 11)",
        1, "truncated_meta", absent=["out"]),
    Row("report", "`--fraction 0`", ["report", "--fraction", "0", "--out", "{tmp}/out"],
        "`--fraction` must be in (0, 1], got 0.0", 2, absent=["out"]),
    Row("report", "`--seeds x`", ["report", "--seeds", "x"], "argument --seeds: invalid int value: 'x'", 2, argparse=True),
    Row("report", "`--out` holds other files", ["report", "--out", "{tmp}/other"],
        "`--out` " + _OTHER % ("seed_*", "other"), 2, "other"),
    # ------------------------------------------------------------------ pix3d / evaluate-folder
    Row("pix3d", "`--root` missing", ["pix3d", "--root", "{tmp}/nowhere", "--checkpoint", "{tmp}/good.ckpt", "--out", "{tmp}/out"],
        "`--root` must be the Pix3D folder (pix3d.json, img/, ...), got '{tmp}/nowhere' (no such folder)", 2, absent=["out"]),
    Row("pix3d", "`--root` without `pix3d.json`", _PIX3D,
        "'{tmp}/pix3d/pix3d.json' does not exist: `root` must hold Pix3D's pix3d.json", 2, "pix3d_empty", absent=["out"]),
    Row("pix3d", "`--root` with a truncated `pix3d.json`", _PIX3D,
        "{tmp}/pix3d/pix3d.json is not valid JSON: Unterminated string starting at: line 1 column 3 (char 2)", 1,
        "pix3d_truncated", absent=["out"]),
    Row("pix3d", "`--checkpoint` missing", ["pix3d", "--root", "{tmp}/pix3d", "--checkpoint", "A={tmp}/none.ckpt", "--out", "{tmp}/out"],
        "`--checkpoint` must be a checkpoint file, got '{tmp}/none.ckpt' (no such file)", 2, "pix3d_empty", absent=["out"]),
    Row("pix3d", "`--checkpoint` truncated", ["pix3d", "--root", "{tmp}/pix3d", "--checkpoint", _TRUNC, "--out", "{tmp}/out"],
        f"`--checkpoint` {_LIGHTNING} '{_TRUNC}': 5000 bytes torch cannot read (a truncated copy, or not a torch file)",
        1, "pix3d_empty", absent=["out"]),
    Row("pix3d", "`--margin 3`", [*_PIX3D, "--margin", "3"], "`--margin` must be in [0, 2], got 3.0", 2, absent=["out"]),
    Row("evaluate-folder", "`--images` missing", [*_FOLDER[:2], "{tmp}/nowhere", *_FOLDER[3:], "--out", "{tmp}/out"],
        "`--images` must be a folder, got '{tmp}/nowhere' (no such folder)", 2, absent=["out"]),
    Row("evaluate-folder", "`--checkpoint` a plain `torch.save` file",
        [*_FOLDER[:-1], "{tmp}/plain.pt", "--out", "{tmp}/out"],
        f"`--checkpoint` {_LIGHTNING} '{{tmp}}/plain.pt': a plain torch.save file holding a dict of 1 keys without "
        "'state_dict' / 'pytorch-lightning_version'; save models with Trainer.fit / trainer.save_checkpoint",
        1, "views", absent=["out"]),
    Row("evaluate-folder", "`--out` a file", [*_FOLDER, "--out", "{tmp}/notes.txt"],
        "`--out` must be a folder (new, empty or an earlier output), got '{tmp}/notes.txt' (a file)", 2, "views"),
    # ------------------------------------------------------------------ robustness
    Row("robustness", "`--ckpt` missing", [*_ROBUST[:2], "{tmp}/none.ckpt", *_ROBUST[3:]],
        "`--ckpt` must be a checkpoint file, got '{tmp}/none.ckpt' (no such file)", 2, absent=["out"]),
    Row("robustness", "`--ckpt` truncated (first 5,000 bytes)", [*_ROBUST[:2], "B=" + _TRUNC, *_ROBUST[3:]],
        f"`--ckpt` {_LIGHTNING} '{_TRUNC}': 5000 bytes torch cannot read (a truncated copy, or not a torch file)",
        1, absent=["out"]),
    Row("robustness", "`--ckpt` NAME repeated", [*_ROBUST[:2], "A={tmp}/good.ckpt", "--ckpt", "A=" + _TRUNC, *_ROBUST[3:]],
        "`--ckpt` NAME 'A' is repeated: every checkpoint needs its own NAME (give one as NAME=CKPT)", 2,
        absent=["out"]),
    Row("robustness", "`--data` missing", _ROBUST,
        "`--data` must be a ShapeNet-VTR directory or `embedded`, got '{tmp}/nowhere' (no such folder)", 2, absent=["out"],
        note="checked before a model loads"),
    Row("robustness", "`--data` a folder of other files", [*_ROBUST[:4], "{tmp}/other", *_ROBUST[5:]],
        _NO_METADATA % ("other", "other"), 2, "other", absent=["out"]),
    Row("robustness", "`--k 7` (does not divide 180)", [*_ROBUST, "--k", "7"],
        "`--k` must be a bin interval K in degrees that divides 180, got 7", 2, absent=["out"]),
    Row("robustness", "`--objects 0`", [*_ROBUST, "--objects", "0"],
        "argument --objects: expected a positive integer, got '0'", 2, argparse=True),
    Row("robustness", "`--out` holds other files", [*_ROBUST[:6], "{tmp}/other"],
        "`--out` " + _OTHER % ("bins.csv", "other"), 2, "other", absent=["other/index.html"]),
    # ------------------------------------------------------------------ fit / validate / test / predict (LightningCLI)
    Row("fit", "`--config` missing", [*_FIT, "{tmp}/none.yaml"],
        "`--config` must be a YAML config file, got '{tmp}/none.yaml' (no such file)", 2),
    Row("fit", "`--config` empty", [*_FIT, "{tmp}/empty.yaml"], _CONFIG % "empty.yaml" + ": an empty file (0 bytes)", 1,
        "configs"),
    Row("fit", "`--config` truncated", [*_FIT, "{tmp}/truncated.yaml"],
        _CONFIG % "truncated.yaml" + ": invalid YAML at line 2, column 1 (expected ',' or ']', but got '<stream "
        "end>'; truncated?)", 1, "configs"),
    Row("fit", "`--config` a binary file", [*_FIT, "{tmp}/good.ckpt"],
        _CONFIG % "good.ckpt" + ": %d bytes that are not UTF-8 text (a binary file)", 1),
    Row("fit", "`--config` a YAML list", [*_FIT, "{tmp}/list.yaml"],
        _CONFIG % "list.yaml" + ": YAML holding a list, not a mapping of settings", 1, "configs"),
    Row("fit", "`--trainer.max_epochs=abc`", ["fit", "--model=lightning_vtr.models.pix2vox.Pix2VoxPlusPlus",
        "--trainer.max_epochs=abc"], 'Parser key "trainer.max_epochs": Does not validate against any of the Union '
        "subtypes Subtypes: [<class 'int'>, <class 'NoneType'>] Errors: - Expected a <class 'int'> - Expected a "
        "<class 'NoneType'> Given value type: <class 'str'> Given value: abc", 2),
    Row("test", "`--ckpt_path` truncated", ["test", "--config", "configs/pix2vox_tiny_vtr.yaml", "--ckpt_path", _TRUNC],
        f"`--ckpt_path` {_LIGHTNING} '{_TRUNC}': 5000 bytes torch cannot read (a truncated copy, or not a torch file)",
        1),
    Row("validate", "`--data.root` missing", ["validate", "--config", "configs/pix2vox_tiny_vtr.yaml",
        "--data.root", "{tmp}/nowhere"], _NO_METADATA % ("nowhere", "nowhere"), 2,
        note="before the Trainer prints its banner"),
    Row("validate", "`data.root` missing, set in a second `--config`", ["validate", "--config",
        "configs/pix2vox_tiny_vtr.yaml", "--config", "{tmp}/root.yaml"], _NO_METADATA % ("nowhere", "nowhere"), 2,
        "configs", note="before the Trainer prints its banner"),
    Row("test", "`--ckpt_path` of the other model class", ["test", "--config", "configs/lrgt_tiny_vtr.yaml",
        "--ckpt_path", "{tmp}/good.ckpt"], "`--ckpt_path` must be a checkpoint of the configured model (LRGT), got "
        "'{tmp}/good.ckpt': a checkpoint of Pix2VoxPlusPlus (hyperparameters merger_lr, betas, two_stage_loss, ... "
        "that LRGT does not take)", 1),
    Row("predict", "(LightningCLI) `--config` missing", ["predict", "--config", "{tmp}/none.yaml"],
        "`--config` must be a YAML config file, got '{tmp}/none.yaml' (no such file)", 2),
    # ------------------------------------------------------------------ unsafe names (no path leaves its root)
    *[Row("predict", f"`--data` {what}", _UNSAFE_DATA, f"{{tmp}}/data/metadata.json: {message}", 1, f"unsafe:{case}",
          absent=["out"], inside="out") for case, (what, message) in _UNSAFE_KEYS.items()],
    Row("build-dataset", "`--source` mesh file `-rf.obj` (generic layout)", ["build-dataset", "{tmp}/new",
        "--source", "{tmp}/meshes", "--no-progress"], "{tmp}/meshes/chair: mesh file '-rf': " + _RULE["dash"], 1,
        "unsafe_mesh", absent=["new/metadata.json"], inside="new"),
    Row("evaluate-folder", "`--images` model folder `-x`", [*_FOLDER, "--out", "{tmp}/out"],
        "{tmp}/views/chair: model folder '-x': " + _RULE["dash"], 1, "unsafe_folder", absent=["out/table.md"],
        inside="out"),
    Row("pix3d", "`pix3d.json` `img` with `..`", _PIX3D,
        "{tmp}/pix3d/pix3d.json, record 0 (../evil.png): key 'img' '../evil.png': " + _RULE["dot"] + " (its part '..')",
        1, "unsafe_pix3d", absent=["out/table.md"], inside="out"),
    Row("predict", "`--out` an earlier output whose object folder is a symlink leading out", _PREDICT,
        "{tmp}/out/views: expected a path inside {tmp}/out, found one that resolves to {tmp}/elsewhere (a name with "
        "'..', an absolute name or a symlink that leads out); nothing was written there", 1, "symlinked_out",
        inside="out", note="the writer's own check: every path it writes is joined with join_under"),
    Row("robustness", "`--out` an earlier output whose `maps/<NAME>` folder is a symlink leading out",
        ["robustness", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/data", "--out", "{tmp}/out", "--k", "90",
         "--objects", "1", "--no-progress", "--device", "cpu"], _LEADS_OUT % ("out/maps/good", "out"), 1,
        "symlinked_maps", absent=["out/index.html"], inside="out",
        note="met when the maps are written, after the measurement; a NAME= label becomes a safe file stem"),
    Row("predict", "(LightningCLI) `VoxelPredictionWriter`'s `output_dir` an earlier output whose view-set folder "
        "is a symlink leading out", ["predict", "--config", "configs/pix2vox_tiny_vtr.yaml", "--data.root",
        "{tmp}/data", "--trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter",
        "--trainer.callbacks.output_dir={tmp}/out", "--trainer.accelerator=cpu", "--trainer.logger=false",
        "--trainer.default_root_dir={tmp}/out"], (_LEADS_OUT % ("out/aligned/chair/chair_0001", "out"))
        .replace("/elsewhere ", "/elsewhere/chair/chair_0001 "), 1, "symlinked_prediction",
        absent=["out/index.html", "out/predictions.json"], inside="out"),
    Row("report", "`--out` an earlier output whose `seed_0` folder is a symlink leading out",
        ["report", "--out", "{tmp}/out", "--seeds", "0"], _LEADS_OUT % ("out/seed_0", "out"), 1, "symlinked_seed",
        absent=["out/report.md"], inside="out", note="before the first fit"),
    Row("report", "`--out` an earlier output whose `seed_0/pretrain` folder is a symlink leading out",
        ["report", "--out", "{tmp}/out", "--seeds", "0"], _LEADS_OUT % ("out/seed_0/pretrain", "out/seed_0"), 1,
        "symlinked_pretrain", absent=["out/report.md"], inside="out", note="before the first fit"),
]  # fmt: skip


# ------------------------------------------------------------------------------------------ setups
def _checkpoints(tmp: Path) -> None:
    """``good.ckpt`` (a tiny Pix2Vox++), ``trunc.ckpt`` (its first 5,000 bytes), ``empty.ckpt``, ``plain.pt``
    (a plain ``torch.save``) and ``notes.txt``."""
    import shutil

    import torch

    shutil.copy(_good_checkpoint(), tmp / "good.ckpt")
    (tmp / "trunc.ckpt").write_bytes((tmp / "good.ckpt").read_bytes()[:5000])
    (tmp / "empty.ckpt").write_bytes(b"")
    torch.save({"weights": torch.zeros(2)}, tmp / "plain.pt")
    (tmp / "notes.txt").write_text("my own notes\n")


_GOOD: list[Path] = []


def _good_checkpoint() -> Path:
    """One tiny Pix2Vox++ checkpoint per test session (written once)."""
    if not _GOOD:
        import tempfile

        import lightning as L
        import torch

        from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

        model = Pix2VoxPlusPlus(preset="tiny")
        checkpoint = {
            "state_dict": model.state_dict(),
            "hyper_parameters": dict(model.hparams),
            "pytorch-lightning_version": L.__version__,
        }
        model.on_save_checkpoint(checkpoint)
        path = Path(tempfile.mkdtemp(prefix="bad_input_table_")) / "good.ckpt"
        torch.save(checkpoint, path)
        _GOOD.append(path)
    return _GOOD[0]


def _picture(path: Path) -> None:
    import numpy as np
    from PIL import Image

    noise = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)  # 3 kB: 200 bytes is a part
    Image.fromarray(noise).save(path)


def _views(tmp: Path, bad: bytes | None = None) -> None:
    (tmp / "views").mkdir()
    _picture(tmp / "views" / "b.png")
    if bad is not None:
        (tmp / "views" / "a.png").write_bytes(bad)


def _truncate(source: Path, target: Path) -> None:
    target.write_bytes(source.read_bytes()[:200])


def _other(tmp: Path) -> None:
    (tmp / "other").mkdir()
    (tmp / "other" / "notes.txt").write_text("not mine")


def _meta(tmp: Path, text: str) -> None:
    (tmp / "data").mkdir()
    (tmp / "data" / "metadata.json").write_text(text)


def _refuse(monkeypatch: pytest.MonkeyPatch, module: Any, name: str, err: int, message: str) -> None:
    def refuse(path: Any, *args: Any, **kwargs: Any) -> Any:
        raise OSError(err, message, str(path))

    monkeypatch.setattr(module, name, refuse, raising=False)


def _refuse_probe(tmp: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The probe file (``tempfile.mkstemp`` in ``--out``, a random name) is refused, as in a read-only folder."""
    import lightning_vtr.utils.io as io

    _views(tmp)

    def refuse(*args: Any, dir: Any = None, prefix: str = "", **kwargs: Any) -> Any:
        raise PermissionError(errno.EACCES, "Permission denied", str(Path(dir, f"{prefix}x7Qz")))

    monkeypatch.setattr(io.tempfile, "mkstemp", refuse)


def _full_export(tmp: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import lightning_vtr.export as export

    _views(tmp)

    def full(directory: Any, *args: Any, **kwargs: Any) -> Any:
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(directory) / "prediction.binvox"))

    monkeypatch.setattr(export, "export_prediction", full)


def _pix3d(tmp: Path, text: str | None) -> None:
    (tmp / "pix3d").mkdir()
    if text is not None:
        (tmp / "pix3d" / "pix3d.json").write_text(text)


def _configs(tmp: Path) -> None:
    (tmp / "empty.yaml").write_text("")
    (tmp / "truncated.yaml").write_text("trainer: [max_epochs\n")
    (tmp / "list.yaml").write_text("- trainer\n- model\n")
    (tmp / "root.yaml").write_text(f"data:\n  root: {tmp / 'nowhere'}\n")


def _unsafe_meta(tmp: Path, case: str) -> None:
    """A metadata.json whose names break one rule (:data:`_UNSAFE_OBJECTS`), in a folder beside the output."""
    import json

    view_sets = ["../aligned"] if case == "view_set" else ["aligned"]
    objects = {key: {"split": "test", "views": {"aligned": [[0.0, 30.0]]}} for key in _UNSAFE_OBJECTS[case]}
    meta = {"format": "lightning_vtr.shapenet_vtr", "version": 1, "objects": objects, "view_sets": view_sets,
            "resolution": 32, "image_size": 64}  # fmt: skip
    (tmp / "data").mkdir()
    (tmp / "data" / "metadata.json").write_text(json.dumps(meta))


def _unsafe_mesh(tmp: Path) -> None:
    (tmp / "meshes" / "chair").mkdir(parents=True)
    (tmp / "meshes" / "chair" / "-rf.obj").write_text("v 0 0 0\n")


def _unsafe_folder(tmp: Path) -> None:
    (tmp / "views" / "chair" / "-x").mkdir(parents=True)
    _picture(tmp / "views" / "chair" / "-x" / "00.png")


def _unsafe_pix3d(tmp: Path) -> None:
    import json

    record = {"img": "../evil.png", "mask": "mask/chair/0001.png", "voxel": "model/chair/a/voxel.mat",
              "category": "chair", "bbox": [0, 0, 10, 10], "img_size": [10, 10],
              "rot_mat": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "trans_mat": [0, 0, 2]}  # fmt: skip
    _pix3d(tmp, json.dumps([record]))


def _symlinked_out(tmp: Path) -> None:
    """An earlier ``predict`` output whose folder for ``views`` is a symlink to a folder outside it."""
    _views(tmp)
    (tmp / "out").mkdir()
    (tmp / "out" / "predictions.json").write_text("[]")
    (tmp / "elsewhere").mkdir()
    (tmp / "out" / "views").symlink_to(tmp / "elsewhere", target_is_directory=True)


def _tiny_data(tmp: Path) -> None:
    """``data``: a ShapeNet-VTR dataset of 3 procedural chairs (one of them, ``chair/chair_0001``, in the test split)."""
    from lightning_vtr.data.builder import build_dataset

    build_dataset(tmp / "data", source="procedural", categories=["chair"], objects_per_category=3, image_size=64,
                  resolution=32, views_per_set=3, progress=False)  # fmt: skip


def _symlinked(tmp: Path, marker: str, link: str, data: bool = False) -> None:
    """An earlier output (``out/<marker>``) whose folder ``out/<link>`` is a symlink to ``elsewhere``."""
    if data:
        _tiny_data(tmp)
    (tmp / "out" / link).parent.mkdir(parents=True)
    if marker:
        (tmp / "out" / marker).write_text("")
    (tmp / "elsewhere").mkdir()
    (tmp / "out" / link).symlink_to(tmp / "elsewhere", target_is_directory=True)


def _lightning_logs_to_stderr(mp: pytest.MonkeyPatch) -> None:
    """Point the console log handlers at this test's ``sys.stderr``: a handler made in an earlier test (Lightning's,
    on import) holds that test's captured stream, closed since (the Trainer's banner would print a logging error)."""
    import logging

    loggers = [
        logging.getLogger(),
        *(v for v in logging.Logger.manager.loggerDict.values() if isinstance(v, logging.Logger)),
    ]
    for handler in (h for logger in loggers for h in logger.handlers):
        if isinstance(handler, logging.StreamHandler) and getattr(handler.stream, "closed", False):
            mp.setattr(handler, "stream", sys.stderr)


SETUPS = {
    "symlinked_maps": lambda tmp, mp: _symlinked(tmp, "bins.csv", "maps/good", data=True),
    "symlinked_prediction": lambda tmp, mp: (_symlinked(tmp, "", "aligned", data=True), _lightning_logs_to_stderr(mp)),
    "symlinked_seed": lambda tmp, mp: _symlinked(tmp, "", "seed_0"),
    "symlinked_pretrain": lambda tmp, mp: _symlinked(tmp, "", "seed_0/pretrain"),
    **{f"unsafe:{case}": (lambda tmp, mp, case=case: _unsafe_meta(tmp, case)) for case in _UNSAFE_OBJECTS},
    "unsafe_mesh": lambda tmp, mp: _unsafe_mesh(tmp),
    "unsafe_folder": lambda tmp, mp: _unsafe_folder(tmp),
    "unsafe_pix3d": lambda tmp, mp: _unsafe_pix3d(tmp),
    "symlinked_out": lambda tmp, mp: _symlinked_out(tmp),
    "": lambda tmp, mp: None,
    "other": lambda tmp, mp: _other(tmp),
    "views": lambda tmp, mp: _views(tmp),
    "views_other": lambda tmp, mp: (_views(tmp), _other(tmp)),
    "not_a_picture": lambda tmp, mp: _views(tmp, b"hello"),
    "truncated_picture": lambda tmp, mp: (_views(tmp), _truncate(tmp / "views" / "b.png", tmp / "views" / "a.png")),
    "empty_picture": lambda tmp, mp: _views(tmp, b""),
    "empty_meta": lambda tmp, mp: _meta(tmp, ""),
    "truncated_meta": lambda tmp, mp: _meta(tmp, '{"format": "lightning_vtr.shap'),
    "other_meta": lambda tmp, mp: _meta(tmp, '{"format": "pix2vox", "version": 1}'),
    "refuse_build": lambda tmp, mp: _refuse(
        mp,
        __import__("lightning_vtr.data.builder").data.builder,
        "atomic_write_json",
        errno.EACCES,
        "Permission denied",
    ),
    "full_build": lambda tmp, mp: _refuse(
        mp, __import__("lightning_vtr.data.builder").data.builder, "atomic_write_json", errno.ENOSPC, "No space left"
    ),
    "refuse_probe": _refuse_probe,
    "full_export": _full_export,
    "pix3d_empty": lambda tmp, mp: _pix3d(tmp, None),
    "pix3d_truncated": lambda tmp, mp: _pix3d(tmp, '[{"img'),
    "configs": lambda tmp, mp: _configs(tmp),
}


# ----------------------------------------------------------------- a model and a selector of the user's own
_USER_MODEL = """
import lightning as L


class NotAModel(L.LightningModule):
    pass


class NoSteps(L.LightningModule):
    image_size, num_views, voxel_resolution = 64, 3, 32

    def predict_voxels(self, images):
        return images.new_zeros(len(images), 32, 32, 32)
"""
_NOT_A_SELECTOR = "mine:\n  title: Mine\n  description: d\n  selector: {class_path: usermodel_bad.NoSteps}\n"
_NO_MODULE = "mine:\n  title: Mine\n  description: d\n  selector:\n    class_path: nosuchmodule.Sel\n"
_SHIPPED_TITLE = "mine:\n  title: Nature\n  description: d\n  selector: random\n"


def _user_files(tmp: Path, mp: pytest.MonkeyPatch) -> None:
    """``usermodel_bad.py`` and strategies files in the working folder, which the commands import from."""
    _views(tmp)
    (tmp / "usermodel_bad.py").write_text(_USER_MODEL)
    for name, text in (("not_selector", _NOT_A_SELECTOR), ("no_module", _NO_MODULE), ("title", _SHIPPED_TITLE)):
        (tmp / f"{name}.yaml").write_text(text)
    mp.chdir(tmp)
    mp.setattr(sys, "path", list(sys.path))  # the working folder the command adds is forgotten after the test
    mp.delitem(sys.modules, "usermodel_bad", raising=False)


SETUPS["user_files"] = _user_files


# ----------------------------------------------------------------- untrusted input that would expand or hide
def _entry_meta(tmp: Path, entry: Any) -> None:
    """A metadata.json whose object ``chair/a`` has the entry ``entry``."""
    import json

    meta = {"format": "lightning_vtr.shapenet_vtr", "version": 1, "objects": {"chair/a": entry},
            "view_sets": ["aligned"], "resolution": 32, "image_size": 64}  # fmt: skip
    _meta(tmp, json.dumps(meta))


def _bomb_picture(tmp: Path) -> None:
    """``views/a.png``: a 100-byte PNG whose header claims 30000 x 30000 pixels."""
    import struct
    import zlib

    from PIL import Image

    _views(tmp)
    Image.new("L", (4, 4)).save(tmp / "views" / "a.png")
    data = bytearray((tmp / "views" / "a.png").read_bytes())
    start = data.index(b"IHDR")
    data[start + 4 : start + 12] = struct.pack(">II", 30000, 30000)
    data[start + 17 : start + 21] = struct.pack(">I", zlib.crc32(bytes(data[start : start + 17])))
    (tmp / "views" / "a.png").write_bytes(bytes(data))


def _large_meta(tmp: Path, mp: pytest.MonkeyPatch) -> None:
    """A valid metadata.json of 200 bytes, over a JSON limit of 100 bytes."""
    _entry_meta(tmp, {"split": "test", "views": {"aligned": [[0.0, 30.0]]}})
    path = tmp / "data" / "metadata.json"
    path.write_text(path.read_text().ljust(200))
    mp.setenv("LIGHTNING_VTR_MAX_JSON_BYTES", "100")


SETUPS["evil_split"] = lambda tmp, mp: _entry_meta(tmp, {"split": "evil", "views": {}})
SETUPS["number_entry"] = lambda tmp, mp: _entry_meta(tmp, 5)
SETUPS["bomb_picture"] = lambda tmp, mp: _bomb_picture(tmp)
SETUPS["large_meta"] = _large_meta
_MANY_VIEWS = "mine:\n  title: Mine\n  description: d\n  selector: random\n  selector_kwargs: {num_views: 1000000}\n"
SETUPS["many_views"] = lambda tmp, mp: (tmp / "many_views.yaml").write_text(_MANY_VIEWS)
ROWS += [
    Row("dataset-info", "`metadata.json` object with `split: \"evil\"`", ["dataset-info", "{tmp}/data"],
        "{tmp}/data/metadata.json: object 'chair/a' has split 'evil', expected one of ('train', 'val', 'test')", 1,
        "evil_split"),
    Row("predict", "`--data` object entry a number", _UNSAFE_DATA, "{tmp}/data/metadata.json: object 'chair/a' must "
        "map to a JSON object of fields, found int", 1, "number_entry", absent=["out"]),
    Row("dataset-info", "`metadata.json` over the JSON size limit (`LIGHTNING_VTR_MAX_JSON_BYTES=100`)",
        ["dataset-info", "{tmp}/data"], "{tmp}/data/metadata.json: a JSON file of at most 100 bytes was expected, "
        "found 200 bytes (set $LIGHTNING_VTR_MAX_JSON_BYTES to read larger files)", 1, "large_meta"),
    Row("predict", "`--images` holds a 100-byte PNG whose header claims 30000x30000 pixels", _PREDICT,
        "`--images`: {tmp}/views/a.png: a picture of at most 8192x8192 pixels was expected, found 900000000 pixels "
        "(more than PIL's decompression-bomb limit of 178956970 pixels); not decoded", 1, "bomb_picture",
        absent=["out"]),
    Row("report", "`--strategies-file` row with `num_views: 1000000`", ["report", "--strategies-file",
        "{tmp}/many_views.yaml", "--out", "{tmp}/out"], "{tmp}/many_views.yaml, row 'mine', selector_kwargs: "
        "`num_views` must be an integer in [1, 64], got 1000000", 1, "many_views", absent=["out"],
        note="before any training"),
]  # fmt: skip


def _planted_voxels(tmp: Path, kind: str) -> None:
    """:func:`_tiny_data` whose test object's ``model.binvox`` is a symlink to ``elsewhere.binvox`` (``"link"``) or
    a FIFO (``"fifo"``), as a tar archive may hold."""
    import os

    _tiny_data(tmp)
    voxel = tmp / "data" / "objects" / "chair" / "chair_0001" / "model.binvox"
    if kind == "link":
        voxel.rename(tmp / "elsewhere.binvox")
        voxel.symlink_to(tmp / "elsewhere.binvox")
    else:
        voxel.unlink()
        os.mkfifo(voxel)


SETUPS["voxels_linked_out"] = lambda tmp, mp: _planted_voxels(tmp, "link")
SETUPS["voxels_fifo"] = lambda tmp, mp: _planted_voxels(tmp, "fifo")
_VOXELS = "{tmp}/data/objects/chair/chair_0001/model.binvox"
_DATA = ["predict", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}/data", "--view-sets", "aligned", "--out",
         "{tmp}/out", "--no-progress"]  # fmt: skip
ROWS += [
    Row("predict", "`--data` an object's `model.binvox` a symlink leading out of the dataset", _DATA,
        _VOXELS + " is a symbolic link leading out of the dataset (to {tmp}/elsewhere.binvox); not read", 1,
        "voxels_linked_out"),
    Row("predict", "`--data` an object's `model.binvox` a FIFO (named pipe)", _DATA,
        _VOXELS + ": a regular file was expected, found a FIFO (named pipe)", 1, "voxels_fifo"),
]  # fmt: skip
_PROTOCOL = "does not satisfy lightning_vtr.ReconstructionModel: missing %s (see lightning_vtr.protocol)"
_ROW = "{tmp}/%s.yaml, row 'mine'"
ROWS += [
    Row("predict", "`--model` a module not found", [*_PREDICT, "--model", "nosuchmodule.Net"],
        "`--model` must be an importable class path module.Class, got 'nosuchmodule.Net': module 'nosuchmodule' not "
        "found (run from the folder holding nosuchmodule.py, or install it)", 2, "user_files", absent=["out"]),
    Row("predict", "`--model` a class the module lacks", [*_PREDICT, "--model", "usermodel_bad.Missing"],
        "`--model` must be an importable class path, got 'usermodel_bad.Missing': usermodel_bad has no 'Missing'", 2,
        "user_files", absent=["out"]),
    Row("predict", "`--model` neither registered nor a class path", [*_PREDICT, "--model", "unet"],
        "`--model` must be pix2vox, lrgt or a class path module.Class, got 'unet'", 2, "user_files"),
    Row("predict", "`--model` a LightningModule without `predict_voxels`", [*_PREDICT, "--model",
        "usermodel_bad.NotAModel"], "`--model` usermodel_bad.NotAModel " + _PROTOCOL % "predict_voxels(images) -> "
        "(B, R, R, R)", 2, "user_files", absent=["out"]),
    Row("robustness", "`--model` a module not found", ["robustness", "--ckpt", "{tmp}/good.ckpt", "--data", "{tmp}",
        "--out", "{tmp}/out", "--model", "nosuchmodule.Net"], "`--model` must be an importable class path "
        "module.Class, got 'nosuchmodule.Net': module 'nosuchmodule' not found (run from the folder holding "
        "nosuchmodule.py, or install it)", 2, "user_files", absent=["out"]),
    Row("fit", "`--model` without its own `training_step` / `configure_optimizers`", ["fit", "--model",
        "usermodel_bad.NoSteps"], "`--model` usermodel_bad.NoSteps " + _PROTOCOL % "training_step, "
        "configure_optimizers", 2, "user_files"),
    Row("report", "`--model` without its own `training_step` / `configure_optimizers`", ["report", "--model",
        "usermodel_bad.NoSteps"], "`--model` usermodel_bad.NoSteps " + _PROTOCOL % "training_step, "
        "configure_optimizers", 2, "user_files"),
    Row("report", "`--strategies` a row no file has", ["report", "--strategies", "none,ours"],
        "`--strategies` names unknown row(s) 'ours' (`--list-strategies` lists the rows; rows of your own: "
        "--strategies-file)", 2, "user_files"),
    Row("report", "`--strategies-file` missing", ["report", "--strategies-file", "{tmp}/none.yaml"],
        "`--strategies-file` must be a YAML file of strategy rows, got '{tmp}/none.yaml' (no such file)", 2,
        "user_files"),
    Row("report", "`--only-strategies-file` without a file", ["report", "--only-strategies-file"],
        "`--only-strategies-file` needs `--strategies-file FILE`", 2, "user_files"),
    Row("report", "`--strategies-file` row: `class_path` not a ViewSelector", ["report", "--strategies-file",
        "{tmp}/not_selector.yaml"], _ROW % "not_selector" + ": usermodel_bad.NoSteps is not a "
        "lightning_vtr.selection.ViewSelector subclass", 1, "user_files"),
    Row("report", "`--strategies-file` row: `class_path` module not found", ["report", "--strategies-file",
        "{tmp}/no_module.yaml"], _ROW % "no_module" + " must be an importable class path module.Class, got "
        "'nosuchmodule.Sel': module 'nosuchmodule' not found (run from the folder holding nosuchmodule.py, or "
        "install it)", 1, "user_files"),
    Row("report", "`--strategies-file` row with a shipped row's title", ["report", "--strategies-file",
        "{tmp}/title.yaml"], "{tmp}/title.yaml: title(s) 'Nature' repeat a shipped row's; choose another title, or "
        "use the shipped row's name to replace it", 1, "user_files"),
]  # fmt: skip


def _fill(text: str, tmp: Path) -> str:
    return text.replace("{tmp}", str(tmp))


def _expected(row: Row, tmp: Path) -> str:
    message = _fill(row.message, tmp)
    if "%d bytes" in message:  # the binary-config row names the checkpoint's size
        message = message % (tmp / "good.ckpt").stat().st_size
    return message


@pytest.mark.parametrize("row", ROWS, ids=[f"{r.command}: {r.bad_input}" for r in ROWS])
def test_a_bad_input_gets_its_one_line_and_exit_status(row, tmp_path, monkeypatch, capsys):
    from lightning_vtr.cli import main

    _checkpoints(tmp_path)
    SETUPS[row.setup](tmp_path, monkeypatch)
    argv = [_fill(word, tmp_path) for word in row.argv]
    before = _files(tmp_path)
    code = main(argv)
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert code == row.code
    lines = captured.err.splitlines()
    expected = _expected(row, tmp_path)
    if row.argparse:
        expected += f" (`lightning-vtr {row.command} --help` lists the options)"
    assert lines[-1] == f"lightning-vtr {row.command}: error: {expected}"
    if row.command not in ("fit", "validate", "test") and "LightningCLI" not in row.bad_input:
        assert lines == lines[-1:]  # one line: no usage, no Lightning banner before it
    for path in row.absent:
        assert not (tmp_path / path).exists(), f"{path} was left behind"
    if row.inside:
        written = _files(tmp_path) - before
        assert [p for p in written if not p.startswith(f"{row.inside}/")] == [], "a file outside the output folder"


def _files(tmp: Path) -> set[str]:
    """Every file under ``tmp`` (symlinks followed), relative to it."""
    import os

    return {
        Path(folder, name).relative_to(tmp).as_posix()
        for folder, _, names in os.walk(tmp, followlinks=True)
        for name in names
    }


# ------------------------------------------------------------------------------------------ the docs table
def docs_table() -> str:
    """The Markdown table of :data:`ROWS` (``docs/bad_input.md`` holds it between its markers)."""
    lines = ["| command | bad input | message (after `lightning-vtr COMMAND: error: `) | exit |", "|---|---|---|---|"]
    for row in ROWS:
        message = row.message.replace("{tmp}", "DIR").replace("%d", "N").replace("|", "\\|")
        message = message.replace("<", "&lt;").replace(">", "&gt;")
        if row.argparse:
            message = f"{message} (`lightning-vtr COMMAND --help` lists the options)"
        if row.note:
            message = f"{message} *({row.note})*"
        command = row.command if row.command != "predict" or "LightningCLI" not in row.bad_input else "predict"
        lines.append(f"| `{command}` | {row.bad_input} | {message} | {row.code} |")
    return "\n".join(lines) + "\n"


DOCS = Path(__file__).resolve().parents[2] / "docs" / "bad_input.md"
_BEGIN, _END = "<!-- table: generated by tests/cli/test_bad_input_table.py -->", "<!-- end of table -->"


def test_the_docs_table_is_the_tested_one():
    text = DOCS.read_text()
    table = text[text.index(_BEGIN) + len(_BEGIN) : text.index(_END)].strip("\n") + "\n"
    assert table == docs_table(), "regenerate: python tests/cli/test_bad_input_table.py --write"


if __name__ == "__main__":
    if "--write" in sys.argv:
        text = DOCS.read_text()
        start, end = text.index(_BEGIN) + len(_BEGIN), text.index(_END)
        DOCS.write_text(text[:start] + "\n" + docs_table() + text[end:])
    else:
        print(docs_table(), end="")
