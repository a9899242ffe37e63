"""warp_modules.build_all: every Warp module of the package built for a device at once."""

import json
import os
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


CHECK_DEVICE = """
import json, sys, warp as wp
from soft_tissue_sim.warp_modules import build_all, cpu_only, package_modules
names = package_modules()
device = wp.get_device(sys.argv[1])
build_all(device)
def built(name, dev):
    return any(key[0] == (None if dev.is_cpu else dev.context) for key in wp.get_module(name).execs)
mods = [n for n in names if wp.get_module(n).kernels]
print(json.dumps({"cpu_only": [n for n in names if cpu_only(n)],
                  "on_device": [n for n in mods if built(n, device)],
                  "on_cpu": [n for n in mods if built(n, wp.get_device("cpu"))]}))
"""


def test_the_modules_that_run_on_the_cpu_alone_are_built_for_it_only(tmp_path):
    """The host's LCP and the blade's geometry say their kernels run on the CPU alone; build_all
    builds them for the CPU whatever the device, and every other module with kernels for the
    device (STS_TEST_DEVICE: on a GPU, the CPU-only modules are not built for it)."""
    device = os.environ.get("STS_TEST_DEVICE", "cpu")
    script = tmp_path / "check_device.py"
    script.write_text(CHECK_DEVICE)
    out = subprocess.run([sys.executable, str(script), device], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    host = {"soft_tissue_sim.contact.pgs", "soft_tissue_sim.cutting.geometry"}
    assert set(res["cpu_only"]) == host
    assert host <= set(res["on_cpu"])
    if device == "cpu":
        assert len(res["on_device"]) >= 5
    else:
        assert not host & set(res["on_device"])
        assert {"soft_tissue_sim.contact.device_lcp", "soft_tissue_sim.dense_inverse"} <= set(res["on_device"])
