"""Every node's parameter defaults, written once (in its table, which reads them from the
settings' dataclasses), agree with its package's config/<node>.yaml: each parameter the
file sets has the table's default, and each parameter of the table is in the file (set, or
commented out where its default depends on the machine)."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from fingerps_calib.calib_parameters import CALIB_PARAMETERS
from fingerps_driver.driver_parameters import driver_parameters
from fingerps_recon.reconstruction.parameters import PARAMETERS as RECON_PARAMETERS
from fingerps_recon.scan.scan_settings import SCAN_PARAMETERS
from fingerps_recon.sessions.recorder_parameters import recorder_parameters
from fingerps_ros.parameter_table import ParameterRow

SRC = Path(__file__).resolve().parents[2] / "src"


def _evaluated(rows: Callable[[Callable[[str], Any]], tuple[ParameterRow, ...]]
               ) -> dict[str, Any]:
    """A table whose defaults read the parameters declared before them, evaluated in
    declaration order."""
    values: dict[str, Any] = {}
    for row in rows(values.__getitem__):
        values[row.name] = row.default_value()
    return values


TABLES: dict[str, tuple[str, Callable[[], dict[str, Any]]]] = {
    "recon": ("fingerps_recon", lambda: {r.name: r.default_value() for r in RECON_PARAMETERS}),
    "scan": ("fingerps_recon", lambda: {r.name: r.default_value() for r in SCAN_PARAMETERS}),
    "recorder": ("fingerps_recon", lambda: {
        r.name: r.default_value() for r in recorder_parameters(lambda t: f"/fingerps/{t}")}),
    "calib": ("fingerps_calib", lambda: {r.name: r.default_value() for r in CALIB_PARAMETERS}),
    "driver": ("fingerps_driver", lambda: _evaluated(driver_parameters)),
}


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(
            a, b, rel_tol=1e-12, abs_tol=0.0)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.parametrize("node", list(TABLES))
def test_the_config_file_carries_every_default_of_the_table(node: str) -> None:
    package, table = TABLES[node]
    text = (SRC / package / "config" / f"{node}.yaml").read_text()
    listed = {name: value for name, value
              in yaml.safe_load(text)[f"/fingerps/{node}"]["ros__parameters"].items()
              if name.split(".")[0] not in ("normal_map", "fingerprint", "depth", "image_raw")
              or "." not in name}  # the compressed companions' rows are image_transport's
    commented = set(re.findall(r"^ {4,}# ([a-z_.0-9]+): ", text, flags=re.MULTILINE))
    defaults = table()
    differ = {name: (value, defaults.get(name, "<not in the table>"))
              for name, value in listed.items()
              if name not in defaults or not _same(value, defaults[name])}
    assert not differ, f"config/{node}.yaml (file, table): {differ}"
    missing = set(defaults) - set(listed) - commented
    assert not missing, f"config/{node}.yaml lacks {sorted(missing)}"


README = SRC.parent / "README.md"
# README cells that give a default in words (what it depends on), not as a value.
IN_WORDS = {("driver", "led_order"), ("calib", "calibration_dir"), ("recorder", "session_name"),
            ("recorder", "topics"), ("recorder", "chunk_size"), ("recorder", "flush_period")}


def _readme_defaults() -> list[tuple[str, str, str]]:
    """(node, parameter, default cell piece) of the README's parameter table, one per
    parameter (a row naming several gives their defaults in order, comma-separated)."""
    rows = []
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 4 or cells[0] not in TABLES:
            continue
        names = re.findall(r"`([a-z_.0-9]+)`", cells[1])
        pieces = [p.strip() for p in re.split(r",\s*(?![^\[]*\])", cells[2])]
        if len(pieces) != len(names):
            pieces = [cells[2]] * len(names)
        rows += [(cells[0], n, p) for n, p in zip(names, pieces, strict=True)]
    return rows


def test_the_readme_table_gives_every_default_of_the_tables() -> None:
    documented = _readme_defaults()
    assert len(documented) > 60  # the table was found
    differ = []
    for node, name, piece in documented:
        defaults = TABLES[node][1]()
        assert name in defaults, f"README names {node}'s {name!r}, which it does not declare"
        if (node, name) in IN_WORDS:
            continue
        value = yaml.safe_load(piece.replace("`", "").replace('""', "''"))
        if isinstance(defaults[name], str) and value is None:
            value = ""
        if not _same(value, defaults[name]):
            differ.append((node, name, piece, defaults[name]))
    assert not differ, f"README (node, parameter, README's default, the table's): {differ}"
