"""warp_modules.build_all: every Warp module of the package built for a device at once."""

import json
import subprocess
import sys

CHECK = """
import json, warp as wp
from soft_tissue_sim.warp_modules import build_all, package_modules
names = package_modules()
def unbuilt():
    out = []
    for name in names:
        m = wp.get_module(name)
        if m.kernels and not any(key[0] is None for key in m.execs):
            out.append(name)
    return out
before = unbuilt()
seconds = build_all("cpu")
print(json.dumps({"before": before, "after": unbuilt(), "seconds": seconds}))
"""


def test_build_all_builds_every_kernel_module_of_the_package(tmp_path):
    """In a fresh interpreter (nothing built yet): the modules with kernels are unbuilt after
    their import, and all built for the CPU after build_all."""
    script = tmp_path / "check.py"  # Warp builds kernels from files, not from `python -c`
    script.write_text(CHECK)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(res["before"]) >= 5, res  # importing builds nothing
    assert res["after"] == [], res
    assert res["seconds"] >= 0.0
