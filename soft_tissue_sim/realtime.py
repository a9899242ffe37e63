"""What an application that steps a simulation in real time sets for its whole process.

Python's cyclic garbage collector runs a full collection from time to time, walking every
object it tracks. A loaded scene holds a couple of hundred thousand (Warp arrays and their
views, kernels, graphs, mesh tables) that live as long as the process, so such a collection in
the middle of a step stalls it many times over a step's length. :func:`freeze_long_lived`
moves what is alive into the collector's permanent generation, which full collections skip;
objects made later are collected as before. It is the application's choice (a process-wide
setting): the ROS node's process makes it once the node is made; the library does not.
"""

from __future__ import annotations

import gc


def freeze_long_lived() -> int:
    """Collect what is garbage now, then freeze every object still alive (``gc.freeze``): call
    it once the scene is loaded (objects its later steps make, such as captured graphs, stay
    with the collector). Returns how many objects are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
