"""Scene names: a bare name (``"default"``, the node's ``scene:=default``) is tried as
``<name>.yaml`` in the scenes directories: the source tree's and an ament prefix's share directory.
"""

import re

import pytest

from soft_tissue_sim.paths import SCENES_DIR, resolve_path
from soft_tissue_sim.scene import read_scene

PKG = "soft_tissue_sim"


# -- bare scene names ------------------------------------------------------------------------

def test_bare_scene_name_is_found_as_yaml_in_the_scenes_directory():
    assert resolve_path("default") == (SCENES_DIR / "default.yaml").resolve()
    assert resolve_path("beam_1200") == (SCENES_DIR / "beam_1200.yaml").resolve()
    cfg, base = read_scene("default")
    assert cfg["name"] == "default" and base == SCENES_DIR.resolve()


def test_a_file_named_as_given_wins_over_the_yaml_suffix(tmp_path, monkeypatch):
    (tmp_path / "default").write_text("name: mine\n")
    monkeypatch.chdir(tmp_path)
    assert resolve_path("default") == (tmp_path / "default").resolve()


def test_a_missing_bare_name_lists_where_it_looked_yaml_included():
    with pytest.raises(FileNotFoundError) as info:
        resolve_path("no_such_scene")
    msg = str(info.value)
    assert "cannot find 'no_such_scene'" in msg
    assert str(SCENES_DIR / "no_such_scene.yaml") in msg and str(SCENES_DIR / "no_such_scene") in msg
    with pytest.raises(FileNotFoundError) as info:  # a name with a suffix is not given another one
        resolve_path("no_such_scene.yml")
    assert "no_such_scene.yml.yaml" not in str(info.value) and "no_such_scene.yaml" not in str(info.value)


def test_bare_scene_name_is_found_through_the_ament_index(tmp_path, monkeypatch):
    pytest.importorskip("ament_index_python")
    (tmp_path / "share/ament_index/resource_index/packages").mkdir(parents=True)
    (tmp_path / "share/ament_index/resource_index/packages" / PKG).write_text("")
    scenes = tmp_path / "share" / PKG / "config" / "scenes"
    scenes.mkdir(parents=True)
    (scenes / "only_installed.yaml").write_text("name: only_installed\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    assert resolve_path("only_installed") == (scenes / "only_installed.yaml").resolve()
    with pytest.raises(FileNotFoundError, match=re.escape(str(scenes / "missing.yaml"))):
        resolve_path("missing")


def test_node_parameter_scene_takes_a_bare_name():
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    from soft_tissue_sim.ros.node import SimNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = SimNode(context=ctx, start=False, cli_args=["--ros-args", "-p", "scene:=test_small"],
                       parameter_overrides=[Parameter("device", value="cpu")])
        try:
            assert node.get_parameter("scene").value == "test_small" and node.sim.name == "test_small"
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
