"""session_records: a recorded session's prints as the records integrators exchange.

Usage::

    ros2 run fingerps_recon session_records BAG --out DIR [--originating-agency ORI]

BAG is a session bag (directory or ``.mcap``) holding recon_node's ``fingerprint`` topic
(``sensor_msgs/Image`` mono8, 500 ppi: recorded by default when recon_node runs with
``fingerprint:=true``). For the k-th print (k = 1, 2, ...), DIR/print_<k>/ receives
``fingerprint.png`` (500 ppi in its pHYs chunk) and the records of
``fingerps_recon.records.print_records``: ``fingerprint.wsq``, ``fingerprint.fmr`` (ISO/IEC
19794-2:2005), ``fingerprint.an2`` (ANSI/NIST-ITL 1-2011; 1.009 TCN ``<bag name>-<k>``, 1.008
ORI ``--originating-agency``). ``records.json`` in DIR lists every print: its time stamp,
NFIQ 2, minutiae count, the files written or why each record was not made.

A print message that is not a mono8 image is listed with the reason and skipped; a damaged
bag is read up to its damage (a warning names the byte range; ``bag_recover`` repairs it).
Bad input (no such bag, no fingerprint messages): one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.records.print_records import make_print_records
from fingerps_recon.records.wsq_image import WSQ_PPI
from fingerps_recon.surface.png_resolution import png_with_resolution
from fingerps_ros.command_line import CommandLineTool
from fingerps_ros.errors import FingerpsError

_PROG = "session_records"
TOOL = CommandLineTool(_PROG, bad_input=(FingerpsError,), failed=(OSError,),
                       failed_context="cannot write the records: ")
IMAGE_TYPE = "sensor_msgs/msg/Image"


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon session_records``; returns the exit code."""
    return TOOL.main(_parser(), run, argv)


def run(args: argparse.Namespace) -> int:
    """Read the bag's prints, write each one's records, then records.json and a summary."""
    from fingerps_recon.sessions.bag_reader import SessionBagReader
    from fingerps_ros import topics
    from fingerps_ros.errors import MessageError
    from fingerps_ros.image_conversion import image_to_array
    from fingerps_ros.time_conversion import time_nanoseconds

    bag = Path(args.bag)
    reader = SessionBagReader(bag, raise_on_damage=False)
    types = reader.topics()
    wanted = [t for t, kind in types.items()
              if kind == IMAGE_TYPE and t.rsplit("/", 1)[-1] == topics.FINGERPRINT]
    if not wanted:
        raise FingerpsReconError(
            f"{bag} holds no {topics.FINGERPRINT} messages (topics: {', '.join(types) or 'none'})"
            f": record a session with recon_node's fingerprint:=true")
    out = Path(args.out)
    name = bag.resolve().name.removesuffix(".mcap")
    listed = []
    for k, message in enumerate(reader.messages(wanted), start=1):
        msg = message.deserialize()
        entry: dict = {"print": k, "topic": message.topic,
                       "stamp_ns": time_nanoseconds(msg.header.stamp)}
        if msg.encoding != "mono8":
            entry["reason"] = f"a print is a mono8 image, this one is {msg.encoding}: skipped"
            listed.append(entry)
            continue
        try:
            image = image_to_array(msg)
        except MessageError as exc:
            entry["reason"] = f"{exc}: skipped"
            listed.append(entry)
            continue
        folder = out / f"print_{k}"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "fingerprint.png").write_bytes(png_with_resolution(image, WSQ_PPI))
        records = make_print_records(image, transaction_control=f"{name}-{k}",
                                     originating_agency=args.originating_agency)
        entry.update(folder=folder.name, width_px=int(image.shape[1]),
                     height_px=int(image.shape[0]),
                     written=["fingerprint.png", *records.write(folder)], **records.report())
        listed.append(entry)
    for damaged in reader.damage:
        print(f"{_PROG}: warning: {bag}: bytes {damaged.start}..{damaged.end} damaged "
              f"({damaged.reason}); the prints before it were read (bag_recover repairs it)",
              file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    (out / "records.json").write_text(json.dumps({"bag": str(bag.resolve()),
                                                  "prints": listed}, indent=2) + "\n")
    for entry in listed:
        if "reason" in entry:
            print(f"print {entry['print']}: {entry['reason']}")
        else:
            print(f"print {entry['print']}: {entry['width_px']}x{entry['height_px']} px, "
                  f"NFIQ 2 {entry['nfiq2']}, {entry['minutiae']} minutiae -> "
                  f"{entry['folder']}/{{{', '.join(entry['written'])}}}")
    print(f"{_PROG}: {len(listed)} prints of {bag} -> {out}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=_PROG, description="Write a recorded session's prints as WSQ images, ISO/IEC "
        "19794-2 minutiae records and ANSI/NIST-ITL transactions.")
    parser.add_argument("bag", help="session bag: directory or .mcap file")
    parser.add_argument("--out", required=True, help="folder for the records")
    parser.add_argument("--originating-agency", default="FINGERPS",
                        help="1.008 ORI and 14.004 SRC of the transactions (default FINGERPS)")
    return parser
