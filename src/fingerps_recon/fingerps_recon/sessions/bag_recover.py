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

from fingerps_recon.errors import BagRecoveryError, FingerpsReconError
from fingerps_recon.sessions.bag_recovery import default_destination, recover_bag
from fingerps_ros.command_line import CommandLineTool

TOOL = CommandLineTool("bag_recover", bad_input=(BagRecoveryError, FingerpsReconError, OSError))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bag_recover",
        description="Recover an unfinished or damaged fingerps session bag into a valid "
                    "rosbag2 MCAP bag, and say what was lost.")
    parser.add_argument("source", help="bag directory or .mcap file to recover")
    parser.add_argument("-o", "--output", default=None,
                        help="bag directory to create (default: <source>_recovered)")
    return parser


def run(options: argparse.Namespace) -> int:
    """Recover the bag and print the report; return the exit status."""
    destination = options.output or default_destination(options.source)
    print(recover_bag(options.source, destination).describe())
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon bag_recover``; returns the exit code."""
    return TOOL.main(build_parser(), run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
