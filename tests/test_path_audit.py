"""No path of the package is built from a name read from data except through ``join_under``.

The audit reads the package's source (``ast``) and flags, per ``module:function``:

* a path join whose appended part is *data-derived*: ``root / entry["name"]``, ``root / record.key``,
  ``root / f"{category}.png"``, ``Path(root, object_id)``, ``root.joinpath(name)``, ``os.path.join(root, key)``;
* a write (``open(..., "w")``, ``.write_text``, ``.write_bytes``, ``.mkdir``, ``atomic_write``, ``save``,
  ``savez``, ``imwrite``, ``torch.save``, ``savefig``, ``to_csv``, ...) whose path argument is data-derived.

*Data-derived* is a syntactic guess: a subscript with a string key (a JSON or batch field) of a variable
that is neither a module constant nor a table of paths, an attribute named like a data name (``.name``, ``.stem``, ``.key``, ``.category``, ``.object_id``,
...), a variable named like one (``name``, ``key``, ``category``, ``object_id``, ...) or an f-string or ``str()``
of any of these. A join written as ``join_under(root, name)`` is not a ``/`` and is never flagged. Every
flagged place either goes away (use ``join_under``) or is listed in :data:`ALLOWED` with the reason it is safe;
an entry that no longer matches anything fails the audit too, so the list stays true.

A second audit finds every raw write (``open(..., "w")``, ``os.open``, ``.write_text``, ``savefig(path)``,
``Image.save(path)``, ``torch.save``, ``os.replace``, copies and links, ...) outside ``lightning_vtr.utils.io``:
each follows a symlink planted at its path, so it must go through that module's helpers, or be listed in
:data:`ALLOWED_WRITES` with the reason it is safe.
"""

from __future__ import annotations

import ast
from pathlib import Path

import lightning_vtr

PACKAGE = Path(lightning_vtr.__file__).parent

DATA_ATTRS = {"name", "stem", "key", "category", "object_id", "model_id", "view_set", "label"}
DATA_NAMES = {"name", "key", "category", "object_id", "oid", "label", "view_set", "model", "taxonomy", "tag"}
DATA_NAMES |= {"image", "voxel", "entry", "record"}
JOIN_CALLS = {"Path", "PurePath", "joinpath", "join"}
WRITE_CALLS = {
    "write_text",
    "write_bytes",
    "mkdir",
    "atomic_write",
    "atomic_open",
    "atomic_write_json",
    "save",
    "savez",
    "savez_compressed",
    "imwrite",
    "savefig",
    "to_csv",
    "export_binvox",
    "export_mesh",
    "save_png",
    "write_binvox",
    "export_prediction",
    "plot_map",
}

#: Flagged ``module:function`` -> why the path it builds stays where it must.
ALLOWED: dict[str, str] = {
    "lightning_vtr.cli.gen_help:main": "writes the package's own help texts; the names are the constant "
    "file names of LIGHTNING_COMMANDS, not data",
    "lightning_vtr.data.format:object_dir": "both names are checked where they are read (load_metadata, "
    "read_object_json, the builder's _discover); the builder writes through join_under, not through it",
    "lightning_vtr.data.format:image_path": "view-set names are checked where they are read (load_metadata, "
    "read_object_json); the index is an int",
    "lightning_vtr.data.dataset:GeneratedDataset.__getitem__": "reads; __init__ checks every entry's names with "
    "check_name",
    "lightning_vtr.data.datamodule:VTRDataModule.load_state_dict": "reads (is_dir); the loop just above checks "
    "each entry's folder name with check_name",
    "lightning_vtr.data.folder_test_set:FolderTestSet._scan": "reads; the taxonomy and model folder names are "
    "checked with check_name in the same loop",
    "lightning_vtr.data.pix3d:_record": "reads; check_relative_path checks img, mask and voxel just above",
    "lightning_vtr.data.shapenet_rendering:ShapeNetRenderingSource._object": "reads; read_split_file checks "
    "the split file's taxonomy and model names",
    "lightning_vtr.data.verify:_check_view_set": "reads; verify_dataset leaves unsafe view-set names out, and "
    "the other name comes from listing the folder itself",
    "lightning_vtr.synthesis.zero123_checkpoint:find_local_weights": "reads (is_file) a model folder's shard "
    "files; writes nothing",
    "lightning_vtr.synthesis.zero123_checkpoint:load_projection": "reads a model folder's weight files; writes nothing",
    "lightning_vtr.utils.paths:join_under": "the check itself: the resolved parent joined with the path's own last "
    "component (replace_link), only compared with the root",
}

#: Functions that write under a folder the user gave, with names from data: each must call join_under.
WRITERS = [
    "lightning_vtr.export:export_prediction",
    "lightning_vtr.export:VoxelPredictionWriter.write_on_batch_end",
    "lightning_vtr.evaluation.predict:export_predictions",
    "lightning_vtr.evaluation.robustness_plot:write_index_html",
    "lightning_vtr.data.dataset:write_generated_sample",
    "lightning_vtr.data.datamodule:VTRDataModule.add_samples",
    "lightning_vtr.data.builder:_build_object",
    "lightning_vtr.synthesis.cache:SynthesisCache.path",
    "lightning_vtr.utils.image_logging:png_path",
]


def data_derived(node: ast.AST) -> bool:
    """Whether an expression looks like a name read from data (see the module docstring)."""
    if isinstance(node, ast.Subscript):
        key = node.slice
        table = node.value.id if isinstance(node.value, ast.Name) else ""
        # A module constant (FOLDERS["x"]) or a table of paths (paths["index"]) holds no name read from data.
        not_data = table.isupper() or any(word in table.lower() for word in ("path", "file", "dir"))
        return isinstance(key, ast.Constant) and isinstance(key.value, str) and not not_data
    if isinstance(node, ast.Attribute):
        return node.attr in DATA_ATTRS
    if isinstance(node, ast.Name):
        return node.id in DATA_NAMES
    if isinstance(node, ast.JoinedStr):
        return any(data_derived(v.value) for v in node.values if isinstance(v, ast.FormattedValue))
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "str":
        return any(data_derived(a) for a in node.args)
    return False


def _call_name(node: ast.Call) -> str:
    func = node.func
    return func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")


def _is_write_open(node: ast.Call) -> bool:
    modes = [a for a in node.args[1:2]] + [k.value for k in node.keywords if k.arg == "mode"]
    return any(isinstance(m, ast.Constant) and isinstance(m.value, str) and set(m.value) & set("wax") for m in modes)


def _path_argument(node: ast.Call) -> ast.AST | None:
    """The argument of a write call that names the file: the receiver of a method, else the path argument."""
    name = _call_name(node)
    if isinstance(node.func, ast.Attribute) and name in ("write_text", "write_bytes", "mkdir", "to_csv"):
        return node.func.value if name != "to_csv" or not node.args else node.args[0]
    if name == "save" and isinstance(node.func, ast.Attribute) and getattr(node.func.value, "id", "") == "torch":
        return node.args[1] if len(node.args) > 1 else None
    if name == "plot_map":
        return node.args[1] if len(node.args) > 1 else None
    return node.args[0] if node.args else None


class _ScopedVisitor(ast.NodeVisitor):
    """An AST visitor that knows the dotted name of the function or class it is in (``scope``)."""

    def __init__(self) -> None:
        self.scope: list[str] = []

    def where(self, module: str) -> str:
        return f"{module}:{'.'.join(self.scope) or '<module>'}"

    def visit_FunctionDef(self, node: ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) -> None:
        self.scope.append(node.name)
        self.generic_visit(node)
        self.scope.pop()

    visit_AsyncFunctionDef = visit_FunctionDef
    visit_ClassDef = visit_FunctionDef


def audit(source: str, module: str) -> dict[str, list[str]]:
    """``{"module:function": [flagged expression, ...]}`` of one module's source."""
    found: dict[str, list[str]] = {}

    class Visitor(_ScopedVisitor):
        def flag(self, node: ast.AST) -> None:
            found.setdefault(self.where(module), []).append(ast.unparse(node))

        def visit_BinOp(self, node: ast.BinOp) -> None:
            if isinstance(node.op, ast.Div) and data_derived(node.right):
                self.flag(node)
            self.generic_visit(node)

        def visit_Call(self, node: ast.Call) -> None:
            name = _call_name(node)
            appended = node.args if name == "joinpath" else node.args[1:]
            if name in JOIN_CALLS and any(data_derived(a) for a in appended):
                self.flag(node)
            is_write = name in WRITE_CALLS or (name == "open" and _is_write_open(node))
            target = _path_argument(node) if is_write else None
            if target is not None and data_derived(target):
                self.flag(node)
            self.generic_visit(node)

    Visitor().visit(ast.parse(source))
    return found


def audit_package() -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        found.update(audit(path.read_text(encoding="utf-8"), module))
    return found


def _function(qualname: str) -> ast.AST:
    module, _, function = qualname.partition(":")
    path = PACKAGE.parent.joinpath(*module.split(".")).with_suffix(".py")
    node: ast.AST = ast.parse(path.read_text(encoding="utf-8"))
    for part in function.split("."):
        node = next(
            n
            for n in ast.iter_child_nodes(node)
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.name == part
        )
    return node


def test_no_path_is_built_from_data_outside_join_under():
    found = audit_package()
    unexplained = {where: exprs for where, exprs in found.items() if where not in ALLOWED}
    assert unexplained == {}, "build these paths with lightning_vtr.utils.paths.join_under, or allow them with a reason"
    stale = sorted(set(ALLOWED) - set(found))
    assert stale == [], "ALLOWED entries that no longer build a path from data: remove them"


def test_the_audit_flags_joins_and_writes_from_data_and_passes_join_under():
    source = """
def bad_div(out, entry):
    return out / entry["name"]
def bad_fstring(out, record):
    return out / f"{record.key}.png"
def bad_path_call(out, object_id):
    return Path(out, "objects", object_id)
def bad_write(name):
    with open(name, "w") as f:
        f.write("x")
def good(out, entry, record):
    p = join_under(out, entry["name"])
    q = out / "index.html" / f"{3:02d}.png"
    with open(record.path) as f:  # a read of a variable: not a join
        pass
    return p, q, MESH_FOLDERS["scheduler"]
"""
    assert set(audit(source, "m")) == {"m:bad_div", "m:bad_fstring", "m:bad_path_call", "m:bad_write"}


def test_writers_under_a_user_folder_call_join_under():
    missing = []
    for qualname in WRITERS:
        calls = {_call_name(n) for n in ast.walk(_function(qualname)) if isinstance(n, ast.Call)}
        if "join_under" not in calls:
            missing.append(qualname)
    assert missing == []


# ------------------------------------------------------------------------------ every write goes through utils.io
#: The one module that may open files for writing, rename and replace them (``lightning_vtr.utils.io``).
WRITE_HELPER = "lightning_vtr.utils.io"
#: Calls that write a file at a path they are given: a write ``open``, ``os.open``, ``Path.write_text`` /
#: ``write_bytes``, matplotlib's ``savefig``, PIL's / numpy's / torch's ``save``, trimesh's ``export``, copies,
#: moves and links. Each one outside :data:`WRITE_HELPER` follows a symlink planted at its path (or truncates
#: a file in place), so it must go through the helper instead.
RAW_WRITES = {
    "write_text",
    "write_bytes",
    "savefig",
    "save",
    "savez",
    "savez_compressed",
    "savetxt",
    "tofile",
    "imwrite",
    "export",
    "save_checkpoint",
    "copy",
    "copy2",
    "copyfile",
    "copytree",
    "move",
    "rename",
    "touch",
    "symlink_to",
    "hardlink_to",
    "symlink",
    "link",
    "mkstemp",
    "NamedTemporaryFile",
}
#: A write into one of these names writes into a file object (one that ``atomic_open`` / ``atomic_save`` opened,
#: or an in-memory ``BytesIO``), not at a path.
FILE_OBJECTS = {"f", "buffer", "buf", "stream", "handle", "fh"}

#: ``module:function`` of a raw write outside the helper -> why it is safe.
ALLOWED_WRITES: dict[str, str] = {
    "lightning_vtr.experiments.training:pretrain": "Lightning's trainer.save_checkpoint writes the scratch "
    "checkpoint itself; the line before removes whatever stood at that path, and the file is then copied "
    "into place with atomic_write",
}


def _raw_write(node: ast.Call) -> bool:
    """Whether ``node`` writes a file at a path without the helper (see :data:`RAW_WRITES`)."""
    name = _call_name(node)
    receiver = node.func.value if isinstance(node.func, ast.Attribute) else None
    owner = receiver.id if isinstance(receiver, ast.Name) else ""
    if name == "open":
        if owner == "os":
            return True
        at = 1 if receiver is None or owner == "io" else 0  # open(path, mode) / io.open(...); path.open(mode)
        modes = [*node.args[at : at + 1], *(k.value for k in node.keywords if k.arg == "mode")]
        return any(
            isinstance(m, ast.Constant) and isinstance(m.value, str) and set(m.value) & set("wax+") for m in modes
        )
    if name == "replace":  # os.replace; str.replace and dataclasses.replace are not writes
        return owner == "os"
    if name not in RAW_WRITES:
        return False
    if name == "save" and owner == "torch":
        target = node.args[1] if len(node.args) > 1 else None
    else:
        target = node.args[0] if node.args else None
    if name == "save_checkpoint":
        return True
    return target is not None and not (isinstance(target, ast.Name) and target.id in FILE_OBJECTS)


def raw_writes(source: str, module: str) -> dict[str, list[str]]:
    """``{"module:function": [raw write call, ...]}`` of one module's source."""
    found: dict[str, list[str]] = {}

    class Visitor(_ScopedVisitor):
        def visit_Call(self, node: ast.Call) -> None:
            if _raw_write(node):
                found.setdefault(self.where(module), []).append(ast.unparse(node))
            self.generic_visit(node)

    Visitor().visit(ast.parse(source))
    return found


def test_every_write_of_the_package_goes_through_the_write_helper():
    found: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        if module != WRITE_HELPER:
            found.update(raw_writes(path.read_text(encoding="utf-8"), module))
    unexplained = {where: calls for where, calls in found.items() if where not in ALLOWED_WRITES}
    assert unexplained == {}, "write through lightning_vtr.utils.io (atomic_write, atomic_save, save_figure, ...)"
    stale = sorted(set(ALLOWED_WRITES) - set(found))
    assert stale == [], "ALLOWED_WRITES entries that no longer write: remove them"


def test_the_write_audit_flags_raw_writes_and_passes_file_objects():
    source = """
def bad_open(path):
    with open(path, "w") as f:
        f.write("x")
def bad_append(log):
    return log.open("a")
def bad_os(path):
    return os.open(path, os.O_WRONLY)
def bad_text(path):
    path.write_text("x")
def bad_fig(fig, out):
    fig.savefig(out / "report.png")
def bad_pil(image, path):
    image.save(path)
def bad_torch(state, path):
    torch.save(state, path)
def bad_replace(tmp, path):
    os.replace(tmp, path)
def bad_copy(a, b):
    shutil.copy(a, b)
def good(path, fig, image, mesh, state):
    with open(path) as src, open(path, "rb") as raw:
        pass
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png")
        image.save(f, format="PNG")
        torch.save(state, f)
        mesh.export(f, file_type="obj")
    data = mesh.export(file_type="obj")
    return "a".replace("a", "b"), replace(state, x=1), data
"""
    flagged = {where.split(":")[1] for where in raw_writes(source, "m")}
    expected = {"bad_open", "bad_append", "bad_os", "bad_text", "bad_fig", "bad_pil", "bad_torch", "bad_replace"}
    assert flagged == expected | {"bad_copy"}
