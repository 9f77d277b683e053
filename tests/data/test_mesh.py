"""Mesh loading: formats, scene merging, up-axis conversion, normalisation, errors naming the file."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from lightning_vtr.data.mesh import MESH_EXTENSIONS, MeshError, convert_up_axis, load_mesh, normalize_mesh, save_mesh


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents).apply_translation(centre)


@pytest.mark.parametrize("ext", ["obj", "off", "ply", "stl", "glb"])
def test_formats_load_and_normalise(tmp_path, ext):
    mesh = _box((4.0, 2.0, 1.0), (10.0, -3.0, 2.0))
    path = tmp_path / f"m.{ext}"
    mesh.export(path)
    out = load_mesh(path)
    np.testing.assert_allclose(out.bounds, [[-0.5, -0.25, -0.125], [0.5, 0.25, 0.125]], atol=1e-6)
    assert len(out.faces) == 12
    out = load_mesh(path, normalize=False)
    np.testing.assert_allclose(out.bounds, mesh.bounds, atol=1e-5)
    np.testing.assert_allclose(load_mesh(path, longest_side=2.0).extents, [2.0, 1.0, 0.5], atol=1e-6)


def test_scene_graph_transforms_are_applied_when_merging(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(
        _box((1.0, 1.0, 1.0)), node_name="a", transform=trimesh.transformations.translation_matrix([3, 0, 0])
    )
    scene.add_geometry(
        _box((1.0, 1.0, 1.0)), node_name="b", transform=trimesh.transformations.translation_matrix([0, 0, 5])
    )
    path = tmp_path / "scene.glb"
    scene.export(path)
    out = load_mesh(path, up_axis="z", normalize=False)
    assert len(out.faces) == 24
    np.testing.assert_allclose(out.bounds, [[-0.5, -0.5, -0.5], [3.5, 0.5, 5.5]], atol=1e-6)


def test_convert_up_axis_rotates_y_to_z_keeping_handedness():
    # A tetrahedron with vertices on the axes: +Y must go to +Z and +Z to -Y, x unchanged.
    tet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    out = convert_up_axis(tet, "y")
    np.testing.assert_allclose(out.vertices, [[0, 0, 0], [1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    # A proper rotation keeps the signed volume (a mirror would negate it) and leaves the input alone.
    assert out.volume == pytest.approx(tet.volume) and tet.vertices[2].tolist() == [0, 1, 0]
    np.testing.assert_allclose(convert_up_axis(tet, "z").vertices, tet.vertices)
    with pytest.raises(ValueError, match=r"`up_axis` must be one of 'y', 'z', got 'x'"):
        convert_up_axis(tet, "x")


def test_load_with_y_up_puts_the_tall_side_on_z(tmp_path):
    path = tmp_path / "tall.obj"
    _box((0.2, 1.0, 0.4)).export(path)  # tall along +Y, as a ShapeNet chair would be
    out = load_mesh(path, up_axis="y")
    np.testing.assert_allclose(out.extents, [0.2, 0.4, 1.0], atol=1e-6)


def test_normalize_mesh_centres_the_bounding_box():
    mesh = trimesh.Trimesh([[1, 1, 1], [3, 1, 1], [1, 2, 1], [1, 1, 5]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    out = normalize_mesh(mesh)
    # Box [1,3]x[1,2]x[1,5]: centre (2, 1.5, 3), longest side 4 -> scale 1/4.
    np.testing.assert_allclose(out.vertices[1], [(3 - 2) / 4, (1 - 1.5) / 4, (1 - 3) / 4])
    np.testing.assert_allclose(out.bounds, [[-0.25, -0.125, -0.5], [0.25, 0.125, 0.5]])
    with pytest.raises(ValueError, match=r"`longest_side` must be a number > 0, got 0.0"):
        normalize_mesh(mesh, 0.0)
    with pytest.raises(TypeError, match=r"`longest_side` must be a number, got str '1'"):
        normalize_mesh(mesh, "1")


def test_colours_survive_loading(tmp_path):
    mesh = _box((1.0, 1.0, 1.0))
    mesh.visual.vertex_colors = np.tile([200, 10, 10, 255], (len(mesh.vertices), 1))
    mesh.export(tmp_path / "c.ply")
    out = load_mesh(tmp_path / "c.ply")
    assert out.visual.kind == "vertex" and (out.visual.vertex_colors[:, 0] == 200).all()


def test_bad_files_raise_mesh_error_naming_the_file(tmp_path):
    (tmp_path / "garbage.obj").write_text("this is not a mesh\nv 1 2\n")
    (tmp_path / "empty.off").write_text("OFF\n0 0 0\n")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    (tmp_path / "corrupt.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    (tmp_path / "mesh.xyz").write_text("1 2 3\n")
    reasons = {
        "garbage.obj": "no triangles",
        "empty.off": "no triangles",
        "nan.obj": "NaN",
        "flat.obj": "flat",
        "corrupt.glb": "could not be parsed",
        "missing.obj": "no such file",
        "mesh.xyz": "unsupported",
    }
    for name, reason in reasons.items():
        with pytest.raises(MeshError, match=reason) as info:
            load_mesh(tmp_path / name)
        assert str(tmp_path / name) in str(info.value) and info.value.path == str(tmp_path / name)
    assert issubclass(MeshError, ValueError)


def test_save_mesh_is_atomic_and_round_trips(tmp_path):
    mesh = normalize_mesh(_box((1.0, 0.5, 0.25)))
    save_mesh(mesh, tmp_path / "out" / "mesh.ply")
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["mesh.ply"]
    np.testing.assert_allclose(load_mesh(tmp_path / "out" / "mesh.ply", normalize=False).bounds, mesh.bounds, atol=1e-6)
    with pytest.raises(ValueError, match=r"`path` must have a mesh extension \(.obj, .off, .ply, .stl, .glb, .gltf\)"):
        save_mesh(mesh, tmp_path / "mesh.txt")


def test_mesh_extensions_are_the_loadable_formats():
    assert MESH_EXTENSIONS == (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")
