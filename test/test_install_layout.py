"""What an installed (non-editable) package looks like, and scene names found through it.

- A bare scene name (``"default"``, the node's ``scene:=default``) is tried as ``<name>.yaml``
  in the scenes directories: the source tree's and an ament prefix's share directory.
- ``pip install --prefix`` (offline, into a temporary prefix, from a copy of the source tree)
  puts the ament index entry, package.xml, the scenes and the meshes under ``share/``; a fresh
  interpreter in another directory, with only that prefix on PYTHONPATH and AMENT_PREFIX_PATH,
  imports the installed copy (not the checkout's editable install), finds ``default`` through
  the ament index and steps it once on Warp's CPU backend.
- ``colcon build`` (only where ``colcon`` is on PATH; CI has none) installs the same layout.
"""

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from soft_tissue_sim.paths import PACKAGE_ROOT, SCENES_DIR, resolve_path
from soft_tissue_sim.scene import read_scene

PKG = "soft_tissue_sim"
REPO = PACKAGE_ROOT
# not copied from the checkout's top level: git, the venv, build outputs, caches
_SKIP_TOP = {".git", ".venv", "build", "install", "log", "dist", ".pytest_cache", ".devstage", ".whl"}


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


# -- an installed package ----------------------------------------------------------------------

def _copy_source(dst: Path) -> Path:
    """The source tree without the venv, build outputs and caches: pip and colcon build in it."""
    def ignore(d, names):
        skip = {n for n in names if n == "__pycache__" or n.endswith((".egg-info", ".pyc"))}
        return skip | (_SKIP_TOP & set(names) if Path(d) == REPO else set())
    shutil.copytree(REPO, dst, ignore=ignore)
    return dst


def _site_packages(prefix: Path) -> Path:
    found = sorted(p.parent.parent for p in prefix.glob(f"**/{PKG}/__init__.py"))
    assert len(found) == 1, f"one installed {PKG} package under {prefix}, found {found}"
    return found[0]


def _assert_share_layout(prefix: Path) -> None:
    share = prefix / "share"
    assert (share / "ament_index/resource_index/packages" / PKG).is_file()
    assert (share / PKG / "package.xml").is_file()
    for src, dst in [("config/scenes", "config/scenes"), ("meshes", "meshes")]:
        shipped = {p.name for p in (REPO / src).iterdir() if p.suffix in (".yaml", ".vtu")}
        assert shipped and shipped <= {p.name for p in (share / PKG / dst).iterdir()}, dst
    assert (share / PKG / "launch" / "sim.launch.py").is_file()


_CHILD = r"""
import json, sys
# the checkout's editable install (a meta path finder of the venv) must not supply any module
sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")]
import numpy as np
import soft_tissue_sim
from soft_tissue_sim import load_scene, paths
out = {"file": soft_tissue_sim.__file__, "scene": str(paths.resolve_path("default"))}
with load_scene("default", device="cpu") as sim:
    s = sim.step()
    out.update(name=sim.config["name"], converged=bool(s.converged), nodes=int(sim.positions().shape[0]),
               finite=bool(np.isfinite(sim.positions()).all()))
out["modules"] = sorted({m.__file__ for n, m in list(sys.modules.items())
                         if n.split(".")[0] == "soft_tissue_sim" and getattr(m, "__file__", None)})
print("RESULT " + json.dumps(out))
"""


def _run_installed(prefix: Path, site: Path, cwd: Path) -> dict:
    """Load 'default' and step it in a fresh interpreter that sees only the installed copy."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "AMENT_PREFIX_PATH")}
    # PYTHONSAFEPATH: the working directory not on sys.path (3.11+; it is a temporary one anyway)
    env.update(PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(prefix), PYTHONNOUSERSITE="1", PYTHONSAFEPATH="1",
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    r = subprocess.run([sys.executable, "-s", "-c", _CHILD], cwd=cwd, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert line, r.stdout[-3000:] + r.stderr[-3000:]
    return json.loads(line[-1][len("RESULT "):])


def _assert_runs_from_the_install(prefix: Path, site: Path, cwd: Path) -> None:
    out = _run_installed(prefix, site, cwd)
    assert Path(out["file"]).resolve().is_relative_to(site.resolve()), out["file"]
    outside = [f for f in out["modules"] if not Path(f).resolve().is_relative_to(site.resolve())]
    assert not outside, f"modules imported from outside the install: {outside}"
    # found through the ament index (AMENT_PREFIX_PATH), not in a source tree
    assert Path(out["scene"]) == (prefix / "share" / PKG / "config/scenes/default.yaml").resolve()
    assert out["name"] == "default" and out["converged"] and out["finite"] and out["nodes"] > 0


def _venv_install() -> list:
    """The running venv's own soft_tissue_sim entries (dist-info, editable finder), to see pip leave them."""
    entries = []
    for p in sorted(Path(sysconfig.get_paths()["purelib"]).glob(f"*{PKG}*")):
        f = p / "RECORD" if p.is_dir() else p
        entries.append((p.name, f.read_text() if f.is_file() else ""))
    return entries


@pytest.fixture(scope="module")
def pip_prefix(tmp_path_factory):
    """``pip install --prefix`` of a copy of the source tree: offline, no dependencies, the venv's setuptools."""
    root = tmp_path_factory.mktemp("pip_install")
    src, prefix = _copy_source(root / "src"), root / "prefix"
    before = _venv_install()
    # --ignore-installed: without it pip uninstalls the venv's own (editable) soft_tissue_sim
    # before writing to the prefix. --isolated: no user pip configuration.
    cmd = [sys.executable, "-m", "pip", "--isolated", "--disable-pip-version-check", "install", "--no-deps",
           "--no-build-isolation", "--no-index", "--no-cache-dir", "--ignore-installed", "--prefix", str(prefix), "."]
    r = subprocess.run(cmd, cwd=src, capture_output=True, text=True, timeout=300)
    assert _venv_install() == before, "pip changed the venv's own soft_tissue_sim installation"
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return prefix


def test_pip_install_puts_the_ament_index_entry_scenes_and_meshes_under_share(pip_prefix):
    _assert_share_layout(pip_prefix)
    site = _site_packages(pip_prefix)
    assert not (site / "config").exists() and not (site / "test").exists()


def test_installed_package_loads_default_through_the_ament_index_and_steps(pip_prefix, tmp_path):
    _assert_runs_from_the_install(pip_prefix, _site_packages(pip_prefix), tmp_path)


@pytest.mark.skipif(shutil.which("colcon") is None,
                    reason="colcon is not on PATH (pip install colcon-core colcon-python-setup-py colcon-ros)")
def test_colcon_build_installs_the_same_share_layout(tmp_path):
    ws = tmp_path / "ws"
    _copy_source(ws / "src" / PKG)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH")}
    r = subprocess.run(["colcon", "build"],  # the workspace holds this package only
                       cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    prefix = ws / "install" / PKG
    _assert_share_layout(prefix)
    assert (prefix / "lib" / PKG / "sim_node").is_file()  # where `ros2 run soft_tissue_sim sim_node` looks
    _assert_runs_from_the_install(prefix, _site_packages(prefix), tmp_path)
