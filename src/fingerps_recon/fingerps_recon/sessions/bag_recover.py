"""``bag_recover``: turn a killed recorder's (or a damaged) bag into a valid one.

    ros2 run fingerps_recon bag_recover bags/fingerps_20250131T120000Z
    ros2 run fingerps_recon bag_recover broken.mcap -o bags/repaired

Reads the MCAP file record by record, skips each damaged chunk and resynchronises on the
next intact one, keeps every message of every intact chunk (channels defined in a damaged
chunk are taken from the file's summary), writes a new bag directory (MCAP with summary +
metadata.yaml) and prints what was kept and what was lost: each damaged byte range and why,
the chunks lost, and the messages lost per topic (exact when the summary survived, else a
lower bound). The verb only assembles options; `fingerps_recon.sessions.bag_recovery` does the work.

Exit codes: 0 recovered (damage or not), 2 bad input (no such bag, not MCAP, destination
exists).
"""

from __future__ import annotations

import argparse
import sys

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.sessions.bag_recovery import BagRecoveryError, default_destination, recover_bag
from fingerps_ros.privacy import start_private_tool

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bag_recover",
        description="Recover an unfinished or damaged fingerps session bag into a valid "
                    "rosbag2 MCAP bag, and say what was lost.")
    parser.add_argument("source", help="bag directory or .mcap file to recover")
    parser.add_argument("-o", "--output", default=None,
                        help="bag directory to create (default: <source>_recovered)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon bag_recover``; returns the exit code."""
    if not start_private_tool("bag_recover"):  # owner-only files (fingerps_ros.privacy)
        return 2
    options = build_parser().parse_args(argv)
    destination = options.output or default_destination(options.source)
    try:
        report = recover_bag(options.source, destination)
    except (BagRecoveryError, FingerpsReconError, OSError) as err:
        print(f"bag_recover: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(report.describe())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
