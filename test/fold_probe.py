"""Run by test_device_preconditioner in a process of its own: a beam on the dense GPU factor,
stepped, then cut once; prints the number of CuPy kernels compiled (or loaded from CuPy's disk
cache) during that first cut. argv: device."""
import sys

from soft_tissue_sim.scene import load_scene
from test_cutting import beam_scene, lengthwise


def main(device: str) -> int:
    import cupy.cuda.compiler as compiler

    cfg = beam_scene(backend="dense")
    cfg["device"] = device
    with load_scene(cfg) as sim:
        for _ in range(3):
            sim.step()
        made = []
        inner = compiler._compile_module_with_cache

        def counted(*args, **kwargs):
            made.append(1)
            return inner(*args, **kwargs)

        compiler._compile_module_with_cache = counted
        try:
            changed = lengthwise(sim, 0.035, 0.08).changed
        finally:
            compiler._compile_module_with_cache = inner
        print(f"changed {int(changed)} folds {sim.preconditioner.correction.folds} compiled {len(made)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
