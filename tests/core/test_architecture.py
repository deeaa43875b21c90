"""The plan of the house (ARCHITECTURE.md), checked on the source: who may import whom, that
the science rooms know nothing of ROS, and that nodes stay thin."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"
PACKAGES = {  # python package -> its folder
    "fingerps_ros": SRC / "fingerps_msgs" / "fingerps_ros",
    "fingerps_recon": SRC / "fingerps_recon" / "fingerps_recon",
    "fingerps_calib": SRC / "fingerps_calib" / "fingerps_calib",
    "fingerps_driver": SRC / "fingerps_driver" / "fingerps_driver",
}
# Each package may import only the packages below it (interfaces and plumbing at the bottom).
MAY_IMPORT = {
    "fingerps_ros": set(),
    "fingerps_recon": {"fingerps_ros"},
    "fingerps_calib": {"fingerps_ros", "fingerps_recon"},
    "fingerps_driver": {"fingerps_ros", "fingerps_recon", "fingerps_calib"},
}
# Known exceptions, each with its reason (ARCHITECTURE.md, "Exceptions").
EXCEPTIONS = {
    # a leaf command: loads calib_node's saved calibration files for --calibration
    ("fingerps_recon.offline.offline_tune", "fingerps_calib"),
}
# Modules of a science room that reach ROS, each with its reason (ARCHITECTURE.md).
ROS_EXCEPTIONS = {
    # a leaf command: its bag input is read with sessions.bag_reader and converted with
    # fingerps_ros.image_conversion (lazily, only for a bag); its DiLiGenT input needs no ROS
    "fingerps_recon.offline.offline_tune",
    # a leaf command: reads a session bag's fingerprint messages with sessions.bag_reader and
    # fingerps_ros.image_conversion (lazily); the records it writes are the records room's
    "fingerps_recon.offline.session_records",
}
# Rooms of plain science: numpy in, numpy out, no ROS.
SCIENCE_ROOMS = (
    "fingerps_recon.photometric", "fingerps_recon.surface", "fingerps_recon.scan",
    "fingerps_recon.offline", "fingerps_recon.records", "fingerps_calib.lights",
    "fingerps_driver.board", "fingerps_driver.cameras", "fingerps_driver.capture",
    "fingerps_driver.simulation",
)
# Plumbing a science room may import (scan.scan_settings holds the scan node's parameter
# table): it imports neither ROS nor any fingerps module, so no ROS comes in through it.
ROS_FREE_PLUMBING = ("fingerps_ros.parameter_table",)
ROS_MODULES = ("rclpy", "sensor_msgs", "std_msgs", "fingerps_msgs", "diagnostic_msgs",
               "rcl_interfaces", "builtin_interfaces", "geometry_msgs", "action_msgs")
MAX_NODE_LINES = 250


def _modules() -> dict[str, tuple[Path, set[str]]]:
    """Every module of the four packages: dotted name -> (file, modules it imports)."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            imported = set()
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    imported.update(alias.name for alias in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    imported.add(node.module)
                    imported.update(f"{node.module}.{alias.name}" for alias in node.names)
            found[name] = (path, imported)
    return found


MODULES = _modules()


def _module_of(imported: str) -> str | None:
    """The fingerps module an import names (``pkg.mod`` of ``from pkg.mod import name``)."""
    while imported and imported not in MODULES:
        imported = imported.rpartition(".")[0]
    return imported or None


def _reached(name: str) -> set[str]:
    """Every import of ``name`` and of the fingerps modules it imports, at any depth."""
    seen, todo, reached = {name}, [name], set()
    while todo:
        for imported in MODULES[todo.pop()][1]:
            reached.add(imported)
            module = _module_of(imported)
            if module is not None and module not in seen:
                seen.add(module)
                todo.append(module)
    return reached


NODES = sorted(name for name in MODULES if name.endswith("_node") or name.endswith("bag_replay"))


def test_the_modules_are_found() -> None:
    assert len(MODULES) > 80 and "fingerps_ros.qos" in MODULES
    assert "fingerps_recon.recon_node" in NODES and "fingerps_driver.driver_node" in NODES


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_no_package_imports_one_above_it(package: str) -> None:
    wrong = sorted(
        f"{name} imports {imported}"
        for name, (_, imports) in MODULES.items() if name.split(".")[0] == package
        for imported in imports
        if (top := imported.split(".")[0]) in PACKAGES and top != package
        and top not in MAY_IMPORT[package] and (name, top) not in EXCEPTIONS)
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("room", SCIENCE_ROOMS)
def test_science_rooms_know_nothing_of_ros(room: str) -> None:
    """Not directly, nor through a fingerps module they import (at any depth; a listed
    exception only not directly)."""
    wrong = sorted(
        f"{name} reaches {imported}"
        for name in MODULES if name == room or name.startswith(room + ".")
        # an exception may reach ROS through what it imports, never import it itself
        for imported in (MODULES[name][1] if name in ROS_EXCEPTIONS else _reached(name))
        if imported.split(".")[0] in ROS_MODULES)
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("module", ROS_FREE_PLUMBING)
def test_ros_free_plumbing_knows_nothing_of_ros(module: str) -> None:
    wrong = sorted(f"{module} imports {imported}" for imported in MODULES[module][1]
                   if imported.split(".")[0] in (*ROS_MODULES, *PACKAGES))
    assert not wrong, "\n".join(wrong)


def test_no_module_imports_a_node() -> None:
    wrong = sorted(f"{name} imports {imported}" for name, (_, imports) in MODULES.items()
                   for imported in imports
                   if any(imported == node or imported.startswith(node + ".") for node in NODES))
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("node", NODES)
def test_nodes_are_thin(node: str) -> None:
    lines = len(MODULES[node][0].read_text().splitlines())
    assert lines <= MAX_NODE_LINES, f"{node}: {lines} lines (at most {MAX_NODE_LINES})"
