"""Point the ROS wheels' exported CMake targets at this machine's include directories.

The ros-jazzy-* wheels were built in a manylinux container; their exported CMake targets
(``share/*/cmake/*Export.cmake``) name that container's Python and numpy include
directories (``/opt/python/cp311-cp311/...``), which do not exist here, so CMake's
generate step fails for any package that builds interfaces. This rewrites those paths to
the running interpreter's include directory and numpy's. Idempotent: a second run finds
nothing to change.
"""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

import numpy

FOREIGN_PREFIX = "/opt/python/cp311-cp311"


def replacements() -> list[tuple[str, str]]:
    """Return (foreign path, local path) pairs, the longest first."""
    py_include = sysconfig.get_paths()["include"]
    if not Path(py_include, "Python.h").is_file():
        sys.exit(f"error: Python headers not found in {py_include}; install python3-dev")
    return [
        (f"{FOREIGN_PREFIX}/lib/python3.11/site-packages/numpy/_core/include",
         numpy.get_include()),
        (f"{FOREIGN_PREFIX}/include/python3.11", py_include),
    ]


def main() -> int:
    prefix = Path(sys.prefix)
    pairs = replacements()
    changed = 0
    for path in sorted((prefix / "share").glob("*/cmake/*.cmake")):
        text = path.read_text()
        if FOREIGN_PREFIX not in text:
            continue
        new = text
        for old, local in pairs:
            new = new.replace(old, local)
        if new != text:
            path.write_text(new)
            changed += 1
    print(f"mend_ros_wheel_cmake: {changed} CMake export file(s) pointed at {prefix}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
